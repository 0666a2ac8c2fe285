"""The notebooks run from top to bottom as a user runs them: a fresh Python process, their
code cells in order in one namespace, compiled with XLA's default flags (the other tests
compile with conftest.py's faster-compiling ones)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from helpers import default_compile_env

NOTEBOOKS = os.path.join(os.path.dirname(__file__), "..", "notebooks")

RUN_CELLS = textwrap.dedent("""
    import json, sys
    import matplotlib
    matplotlib.use("Agg", force=True)
    name = sys.argv[1]
    with open(name) as f:
        nb = json.load(f)
    namespace = {"__name__": "__main__"}
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] == "code":
            exec(compile("".join(cell["source"]), f"{name}[cell {i}]", "exec"), namespace)
""")


@pytest.mark.parametrize("name", sorted(f for f in os.listdir(NOTEBOOKS) if f.endswith(".ipynb")))
def test_notebook_runs(name, tmp_path):
    r = subprocess.run([sys.executable, "-c", RUN_CELLS,
                        os.path.abspath(os.path.join(NOTEBOOKS, name))],
                       cwd=tmp_path, capture_output=True, text=True, timeout=280,
                       env=default_compile_env())
    assert r.returncode == 0, r.stderr[-3000:]
