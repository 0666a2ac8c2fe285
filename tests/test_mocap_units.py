"""Motion capture in the wrong unit, or beyond what any joint can reach: named with its likely
cause and the fix, in every container (``mocap.csv``, OpenSim ``.sto``/``.mot``, XDF).

The real case behind it: opensim-models' Gait2392 RRA kinematics file says ``inDegrees=no``
while its lumbar angles are degrees (a few of them), so every number stays below 2 pi and the
2 pi check cannot see it; read as radians, the truth reached 259 deg."""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pytest
from helpers import error_of
from test_containers import (
    T0,
    meta_of,
    mocap_stream,
    sensor_stream,
    small_session,
    write_meta,
    write_mot,
    xdf_folder,
)

from kckf_jax import Session, SimConfig, read_session, simulate, write_session
from kckf_jax._sessions._session import SessionWarning
from kckf_jax.cli import main

DEG = 180.0 / math.pi
#: What Gait2392's lumbar coordinates hold (degrees), written where radians are said.
LUMBAR = {"theta1_x": "lumbar_bending", "theta2_y": "lumbar_extension"}


def bent(s: Session, peak: float) -> np.ndarray:
    """``s``'s motion capture scaled so that its largest |joint angle| is ``peak``."""
    K = s.robot.n_joint_axes
    return s.mocap * (peak / np.abs(s.mocap[:, :K]).max())


def storage_folder(tmp_path, numbers: np.ndarray, in_degrees: str, name="mocap.sto",
                   **meta) -> str:
    """A session of ``small_session``'s sensors with ``numbers`` (as written) in an OpenSim
    file under Gait2392's names."""
    s = small_session()
    folder = tmp_path / "s"
    write_session(s, folder)
    os.remove(folder / "mocap.csv")
    write_meta(folder, {**meta_of(folder), "mocap_columns": LUMBAR, **meta})
    cols = {LUMBAR.get(n, n): numbers[:, k] for k, n in enumerate(s.robot.angle_names)}
    write_mot(folder / name, s.mocap_t, cols, in_degrees=in_degrees)
    return str(folder)


def warned(folder, **kwargs) -> list[str]:
    with pytest.warns(SessionWarning) as got:
        read_session(folder, **kwargs)
    return [str(w.message) for w in got]


def test_degrees_in_a_storage_file_that_says_radians(tmp_path):
    s = small_session()
    numbers = bent(s, 4.52)  # degrees: under 2 pi as numbers, 259 deg as radians
    folder = storage_folder(tmp_path, numbers, "no")
    finding = (
        f"{folder}/mocap.sto, columns 'theta1_x' ('lumbar_bending' in the file), 'theta2_y' "
        "('lumbar_extension' in the file): |angle| reaches 4.52 rad (259 deg), beyond any "
        "joint's reach (+-120 deg, joint_range_rad): the file says inDegrees=no but its "
        "numbers look like degrees (max 4.52): fix the header to inDegrees=yes; if the joints "
        'do reach that far, state it in meta.json ("joint_range_rad": rad)')
    assert warned(folder) == [finding]  # kckf filter: said, and read
    assert error_of(folder, require_mocap=True) == f"{finding}, or pass --accept-implausible"
    assert read_session(folder, require_mocap=True, plausible=False).has_truth  # accepted
    fixed = storage_folder(tmp_path / "fixed", numbers, "yes")  # the fix it names
    np.testing.assert_allclose(read_session(fixed, require_mocap=True).mocap, numbers / DEG,
                               rtol=1e-12)


def test_degrees_beyond_2_pi_in_a_storage_file_name_the_header(tmp_path):
    s = small_session()
    folder = storage_folder(tmp_path, bent(s, 25.0), "no", name="mocap.mot")
    message = error_of(folder)
    assert message.startswith(f"{folder}/mocap.mot, column 'theta1_x': |angle| reaches ")
    assert message.endswith("beyond 2 pi (angles must be in rad; degrees?); the file says "
                            "inDegrees=no but its numbers look like degrees: fix the header to "
                            "inDegrees=yes, or pass --accept-implausible")


def test_degrees_in_mocap_csv(tmp_path):
    s = small_session()
    write_session(Session(s.robot, s.t, s.gyro, s.hall_v, 100.0, s.mocap_t, bent(s, 3.0)),
                  tmp_path / "s")
    folder = str(tmp_path / "s")
    assert warned(folder) == [
        f"{folder}/mocap.csv, columns 'theta1_x', 'theta2_y': |angle| reaches 3 rad (172 deg), "
        "beyond any joint's reach (+-120 deg, joint_range_rad): mocap.csv is in rad "
        "(session-format.md); these look like degrees (max 3): convert them to rad; if the "
        'joints do reach that far, state it in meta.json ("joint_range_rad": rad)']
    write_session(Session(s.robot, s.t, s.gyro, s.hall_v, 100.0, s.mocap_t, bent(s, 30.0)),
                  tmp_path / "big")
    assert error_of(tmp_path / "big").endswith(
        "beyond 2 pi (angles must be in rad; degrees?); mocap.csv is in rad (session-format.md); "
        "these look like degrees: convert them to rad, or pass --accept-implausible")


def simulated(tmp_path, range_deg: float | None, numbers=None, in_degrees: str | None = None,
              **meta) -> str:
    """A simulated session (the gyros and the motion capture of one motion) with its motion
    capture as written by ``numbers(mocap)`` in ``mocap.csv`` (``in_degrees`` None) or in
    ``mocap.sto`` with that header."""
    cfg = SimConfig(motion_range_deg=range_deg) if range_deg else SimConfig()
    s = simulate("x,y", "cyclic", seed=1, duration_s=10.0, config=cfg)
    # The simulator states the reach of a robot simulated beyond 120 deg; a lab's meta.json
    # may not: left out here, so the reach is the default's unless ``meta`` gives it.
    s = dataclasses.replace(s, limits=None)
    folder = tmp_path / f"sim{range_deg}{in_degrees}"
    write_session(s, folder)
    write_meta(folder, {**meta_of(folder), **meta})
    if in_degrees is not None:
        os.remove(folder / "mocap.csv")
        cols = dict(zip(s.robot.angle_names, numbers(s.mocap).T))
        write_mot(folder / "mocap.sto", s.mocap_t, cols, in_degrees=in_degrees)
    return str(folder)


def test_a_joint_that_does_reach_that_far(tmp_path):
    """140 deg of real motion: the gyros agree with it, so the finding says to state the
    reach (against the default 120 deg); where meta.json states it, not a word."""
    folder = simulated(tmp_path, 140.0)
    (said,) = warned(folder)
    assert said.startswith(f"{folder}/mocap.csv, column 'theta1_x': |angle| reaches 2.4")
    assert "(14" in said and " deg), beyond any joint's reach (+-120 deg, " in said
    assert said.endswith("the gyros agree with these angles in rad (their rate x0.99), so the "
                         "joint does move that far: state its reach in meta.json "
                         '("joint_range_rad": rad)')
    folder = simulated(tmp_path / "stated", 140.0, joint_range_rad=150 / DEG)
    assert read_session(folder, require_mocap=True).has_truth  # no warning: an error here


def test_the_gyros_tell_degrees_from_radians(tmp_path):
    """A small motion (6 deg) written in degrees under inDegrees=no: the gyros turn 57 times
    slower than its numbers as radians. Written in radians under inDegrees=yes (a real 20 deg
    motion): 57 times faster than its numbers as degrees, named though no angle is out of
    reach. The same small motion in degrees under inDegrees=yes is read without a word."""
    folder = simulated(tmp_path, 6.0, lambda m: m * DEG, "no")
    (said,) = warned(folder)
    assert ("the file says inDegrees=no but its numbers look like degrees (max 5.721): fix the "
            "header to inDegrees=yes (the gyros turn 55 times slower than these numbers as rad)"
            in said), said
    folder = simulated(tmp_path, None, lambda m: m, "yes")
    finding = (f"{folder}/mocap.sto, columns 'theta1_x', 'theta2_y': the gyros turn 58 times "
               "faster than these angles in deg (a factor 57 is radians read as degrees): the "
               "file says inDegrees=yes but its numbers look like radians: fix the header to "
               "inDegrees=no")
    assert warned(folder) == [finding]
    assert error_of(folder, require_mocap=True) == f"{finding}, or pass --accept-implausible"
    assert read_session(simulated(tmp_path, 6.0, lambda m: m * DEG, "yes"), require_mocap=True)


def test_degrees_beyond_any_reach_point_at_the_columns(tmp_path):
    """In degrees, as the file says, and still beyond reach: no unit explains it."""
    s = small_session()
    folder = storage_folder(tmp_path, bent(s, 150.0), "yes", name="mocap.mot")
    (said,) = warned(folder)
    assert "|angle| reaches 150 deg, beyond any joint's reach (+-120 deg, " in said
    assert ("in no unit would that be within reach: check which of the file's columns holds "
            "which angle (meta.json's mocap_columns)") in said


def test_degrees_in_an_xdf_stream_without_units(tmp_path):
    s = small_session()
    numbers = bent(s, 5.0)
    stream = mocap_stream(s, unit="", values=numbers, stamps=s.mocap_t + T0,
                          clock_offsets=[(T0 + k, 0.0) for k in range(3)])
    folder = xdf_folder(tmp_path / "s", s, [sensor_stream(s), stream])
    (said,) = warned(folder)
    assert said.startswith(f"{folder}/recording.xdf, columns 'theta1_x', 'theta2_y': |angle| "
                           "reaches 5 rad (286 deg)")
    assert ("its channels' unit is rad (no unit means rad) but their numbers look like degrees "
            "(max 5): give the channels the unit deg") in said


@pytest.mark.filterwarnings("default::kckf_jax._sessions._session.SessionWarning")
def test_evaluate_refuses_and_filter_says_it_once(tmp_path, capsys):
    s = small_session()
    folder = storage_folder(tmp_path, bent(s, 4.52), "no")
    assert main(["evaluate", folder, "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert err.startswith(f"kckf evaluate: error: {folder}/mocap.sto, columns 'theta1_x'")
    assert "fix the header to inDegrees=yes" in err and "--accept-implausible" in err
    assert main(["filter", folder, "-o", str(tmp_path / "est.csv"), "--quiet"]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(said) == 1 and said[0].startswith(
        f"kckf filter: warning: {folder}/mocap.sto, columns 'theta1_x'")
    assert "fix the header to inDegrees=yes" in said[0]
