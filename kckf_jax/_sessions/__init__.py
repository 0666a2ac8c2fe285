"""Sessions: the interchange format and its containers (CSV, XDF, OpenSim Storage), atomic writes,
and the simulator that makes sessions."""
