"""A Hall sensor drifting slowly from its partner (``kk.hall_drift``): named with its size,
never on a clean recording, under the linear and the exact kinematics (issue 45, item 6)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._readings._drift import MIN_DRIFT_DEG
from kckf_jax.cli import main


@pytest.mark.parametrize("kinematics", ["linear", "exact"])
def test_clean_pairs_do_not_drift(kinematics):
    for joints, kind in (("x,y,x,y", "cyclic"), ("x,y,z", "walking"), ("xyz,xyz", "human")):
        for seed in (1, 2):
            s = kk.simulate(joints, kind, seed, 30.0, kinematics=kinematics)
            p = kk.Params.paper_defaults(s.robot, s.hall_models)
            assert kk.hall_drift(s, p) == [], (joints, kind, seed)


@pytest.mark.parametrize("spec,columns", [("drift:hall2_y_r=0.25", "hall2_y"),
                                          ("drift:hall1_x_l@10-30=-0.25", "hall1_x")])
def test_a_drifting_sensor_is_named_with_its_size(spec, columns, tmp_path, capsys):
    s = kk.simulate("x,y,x,y", "cyclic", 3, 30.0, device_seed=3)
    bad = kk.inject_faults(s, [kk.Fault.parse(spec)])
    before = np.nanmax(np.abs(bad.hall_v - s.hall_v))
    assert 0.24 < before < 0.26  # the fault as written: 0.25 V at its end
    kk.write_session(bad, tmp_path / "s")
    assert main(["evaluate", str(tmp_path / "s"), "--json"]) == 0
    out = capsys.readouterr()
    found = json.loads(out.out)["hall_drift"][str(tmp_path / "s")]
    assert [f["columns"] for f in found] == [[f"{columns}_l", f"{columns}_r"]], found
    assert abs(found[0]["drift_deg"]) > MIN_DRIFT_DEG  # 10-18 deg for 0.25 V
    assert "drifts slowly from its partner" in out.err
