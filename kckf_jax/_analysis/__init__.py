"""Analysis: error figures, diagnostics, their statistics, observability."""
