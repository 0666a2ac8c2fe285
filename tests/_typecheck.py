"""The runtime type checker the test suite applies to the whole package (see conftest.py).

beartype with the PEP 484 numeric tower, so that an ``int`` is accepted where a ``float`` is
annotated (``duration_s=60``), as the typing spec allows.
"""

from beartype import BeartypeConf, beartype

typechecker = beartype(conf=BeartypeConf(is_pep484_tower=True))
