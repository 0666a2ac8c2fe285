"""Every benchmark script runs, end to end: its quick mode (``--quick --json``: every case on
tiny sizes, the figures meaningless) in a fresh process, so that a change that breaks a
benchmark is seen the day it lands (issue 46). Long tests (``pytest -m long``; ``.ci/run``
runs them): about five minutes for all of them on 2 cores."""

from __future__ import annotations

import glob
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Every script in benchmarks/ (modules starting with ``_`` are their shared helpers): a new
#: script without a quick mode fails here.
SCRIPTS = sorted(os.path.basename(p) for p in glob.glob(os.path.join(ROOT, "benchmarks", "*.py"))
                 if not os.path.basename(p).startswith("_"))


def test_every_benchmark_is_here():
    assert "stream_latency.py" in SCRIPTS and len(SCRIPTS) >= 15


@pytest.mark.long
@pytest.mark.timeout(400)
@pytest.mark.parametrize("script", SCRIPTS)
def test_benchmark_quick_mode_runs(script, tmp_path):
    proc = subprocess.run([sys.executable, os.path.join("benchmarks", script), "--quick",
                           "--json"], cwd=ROOT, capture_output=True, text=True, timeout=380,
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    assert proc.returncode == 0, f"{script} --quick --json: exit {proc.returncode}\n" \
                                 f"{proc.stderr[-4000:]}"
    out = proc.stdout.strip()
    assert out, f"{script} --quick --json printed nothing"
    try:
        doc = json.loads(out)
    except json.JSONDecodeError:
        doc = json.loads(out.splitlines()[-1])
    assert doc, f"{script}: an empty result"
