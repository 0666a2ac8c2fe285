"""The readings and their checks: the plausibility screen, the health monitor, gaps, the set-up
check, and what is named after the filter (model mismatch, bias steps, drift); the fault policy;
padding series into a batch."""
