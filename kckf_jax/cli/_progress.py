"""A progress bar for the ``kckf`` command (the edge: only ``cli/__init__.py`` uses it)."""

from __future__ import annotations

import sys
import time


class Progress:
    """A small progress bar on stderr, shown only on a terminal and without ``--quiet``."""

    def __init__(self, total: int, label: str, quiet: bool = False):
        self.total, self.label, self.n = max(total, 1), label, 0
        self.on = not quiet and sys.stderr.isatty()
        self.start = time.perf_counter()

    def update(self, n: int = 1, info: str = "") -> None:
        self.n += n
        if self.on:
            frac = min(self.n / self.total, 1.0)
            bar = "#" * int(30 * frac)
            el = time.perf_counter() - self.start
            sys.stderr.write(f"\r{self.label} [{bar:<30}] {self.n}/{self.total} {el:5.1f}s {info}")
            sys.stderr.flush()

    def close(self) -> None:
        if self.on:
            sys.stderr.write("\n")
