"""Issue #3's claims, on small versions of the recipes in training/ (the full-size runs are
quoted in docs/fitting.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from helpers import default_compile_env

ROOT = os.path.join(os.path.dirname(__file__), "..")


@pytest.mark.long
def test_recovery_of_known_parameters(tmp_path):
    """Hall coefficients perturbed by up to +-10 % per sensor, fit from the paper defaults:
    the fused Hall measurement of every joint is recovered to 1 deg RMS and the fitted
    filter's held-out RMSE is within 5 % of (here: below) the true-parameter filter's."""
    with open(os.path.join(ROOT, "training", "configs", "recovery.json")) as f:
        cfg = json.load(f)
    cfg.update(train_seeds=[500, 501, 502], test_seeds=[600, 601], duration_s=30.0, steps=120)
    (tmp_path / "cfg.json").write_text(json.dumps(cfg))
    out = tmp_path / "out.json"
    r = subprocess.run([sys.executable, os.path.join(ROOT, "training", "recovery.py"),
                        "--config", str(tmp_path / "cfg.json"), "--out", str(out)],
                       capture_output=True, text=True, timeout=600, env=default_compile_env())
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(out.read_text())
    m = res["heldout_mean_rmse_deg"]
    assert m["fitted"] <= 1.05 * m["true"], m
    assert m["fitted"] < 0.3 * m["paper"], m
    for joint, err in res["fused_hall_error_deg"]["fitted"].items():
        assert err < 1.0, (joint, err)
        assert err < 0.5 * res["fused_hall_error_deg"]["paper"][joint]
