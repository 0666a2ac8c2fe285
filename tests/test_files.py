"""Files appear whole or not at all, the CSV reader's fallback reads what its fast path reads,
and no raw Python warning reaches a user."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from kckf_jax import Robot, read_session, simulate, write_session
from kckf_jax._sessions import _atomic, _csvio
from kckf_jax.cli import main

ROBOT = Robot.from_spec("x,y")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("files") / "s")
    write_session(simulate(ROBOT, "cyclic", seed=4, duration_s=6.0, drop_prob=0.5), path)
    return path


def _leftovers(folder):
    return [n for n in os.listdir(folder) if n.endswith(".part")]


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    p = tmp_path / "a.csv"
    p.write_bytes(b"old,whole\n")
    os.chmod(p, 0o640)
    with pytest.raises(KeyboardInterrupt):
        with _atomic.atomic_write(p) as f:
            f.write("new,but")
            raise KeyboardInterrupt
    assert p.read_bytes() == b"old,whole\n" and not _leftovers(tmp_path)
    with _atomic.atomic_write(p) as f:
        f.write("new,whole\n")
    assert p.read_bytes() == b"new,whole\n" and os.stat(p).st_mode & 0o777 == 0o640


@pytest.mark.parametrize("where", ["fsync", "replace"])
def test_interrupted_filter_leaves_the_previous_estimates(folder, tmp_path, monkeypatch, where):
    out = tmp_path / "est.csv"
    out.write_bytes(b"t,theta1_x\n0.0,0.5\n")
    before = out.read_bytes()

    def die(*args, **kwargs):
        raise KeyboardInterrupt  # killed at the worst moment: everything written but renamed

    monkeypatch.setattr(_atomic.os, where, die)
    assert main(["filter", folder, "-o", str(out), "--quiet"]) == 130
    assert out.read_bytes() == before and not _leftovers(tmp_path)


def test_killed_filter_leaves_a_whole_file(folder, tmp_path):
    """SIGKILL as soon as the temporary file appears: the previous file stays byte for byte
    (or, if the command won the race, the new file is whole)."""
    out = tmp_path / "est.csv"
    out.write_bytes(b"t,theta1_x\n0.0,0.5\n")
    before = out.read_bytes()
    proc = subprocess.Popen([sys.executable, "-m", "kckf_jax", "filter", folder, "-o",
                             str(out), "--quiet"], stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    killed = False
    while proc.poll() is None and time.time() < deadline:
        if _leftovers(tmp_path):
            proc.send_signal(signal.SIGKILL)
            killed = True
            break
        time.sleep(0.0005)
    proc.wait(timeout=60)
    if killed:
        assert out.read_bytes() == before
    else:
        assert proc.returncode == 0
        rows = out.read_text().splitlines()
        assert rows[0].startswith("t,") and len(rows) == read_session(folder).n_steps + 1


def test_csv_fallback_reads_what_pyarrow_reads(folder, monkeypatch):
    fast = read_session(folder)
    monkeypatch.setattr(_csvio, "_parse_arrow", lambda *a: None)
    slow = read_session(folder)
    for name in ("t", "gyro", "hall_v", "mocap_t", "mocap"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name))
    assert np.isnan(fast.hall_v).mean() > 0.3  # the empty cells came through as NaN


@pytest.mark.parametrize("text", ["t,a\n0.1,x\n", "t,a\n0.1,NULL\n", "t,a\n0.1,1,3\n"])
def test_pyarrow_refuses_what_the_format_refuses(tmp_path, text):
    p = tmp_path / "x.csv"
    p.write_text(text)
    with pytest.raises(_csvio.SessionError, match=r"x\.csv, line 2"):
        _csvio._read_csv(str(p), ("t", "a"), (), "")


def test_no_raw_warning_reaches_the_user(folder, capsys):
    """Half the readings missing: rows where no Hall reading was used have no NIS; the
    command says nothing raw about them."""
    assert main(["evaluate", folder, "--json"]) == 0
    err = capsys.readouterr().err
    assert "Warning" not in err and "Mean of empty slice" not in err


def test_estimates_csv_reads_back_exactly(folder, tmp_path):
    """``kckf filter -o``'s numbers are the shortest text of each estimate in its own type
    (float64 here: the tests run with x64; float32 for the command's users): read back, the
    same values, and the same times."""
    from kckf_jax import Auto, filter_sessions

    out = tmp_path / "est.csv"
    assert main(["filter", folder, "-o", str(out), "--quiet"]) == 0
    s = read_session(folder)
    est = filter_sessions([s], "kckf", path=Auto(runs=1))[0]  # the command's policy
    header = out.read_text().splitlines()[0].split(",")
    back = _csvio._read_csv(str(out), header, (), "")
    np.testing.assert_array_equal(back["t"], s.t)
    for k, name in enumerate(s.robot.angle_names):
        np.testing.assert_array_equal(back[name].astype(est.angles.dtype), est.angles[:, k])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_columns_writer_round_trips_its_type(tmp_path, dtype, monkeypatch):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.009, 0.011, 500))
    v = (rng.normal(size=(500, 3)) * 10.0 ** rng.integers(-6, 4, (500, 3))).astype(dtype)
    v[::7, 1] = np.nan
    for arrow in (True, False):
        if not arrow:
            monkeypatch.setitem(sys.modules, "pyarrow", None)  # the fallback
        p = str(tmp_path / f"v{arrow}.csv")
        _csvio._write_columns(p, ["t", "a", "b", "c"], t, v)
        back = _csvio._read_csv(p, ("t", "a", "b", "c"), (), "")
        np.testing.assert_array_equal(back["t"], t)
        got = np.stack([back[n] for n in "abc"], axis=1).astype(dtype)
        np.testing.assert_array_equal(got, v)
