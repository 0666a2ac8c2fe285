"""The ``kckf-session/1`` reader, writer, validation messages and mocap alignment."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from helpers import error_of

from kckf_jax import (
    Robot,
    Session,
    align_mocap,
    read_session,
    write_session,
)
from kckf_jax._sessions import _csvio, _session

SPEC = "x,y,x,y"


# ---------------------------------------------------------------------- helpers


def write_files(folder, *, meta=None, sensors=None, mocap=None) -> str:
    """Write a session folder from raw text (``meta`` may be a dict); returns its path."""
    os.makedirs(folder, exist_ok=True)
    for name, text in (("meta.json", meta), ("sensors.csv", sensors), ("mocap.csv", mocap)):
        if text is not None:
            if isinstance(text, dict):
                text = json.dumps(text)
            with open(os.path.join(folder, name), "w", encoding="utf-8", newline="") as f:
                f.write(text)
    return str(folder)


def meta_dict(spec: str = SPEC, **extra) -> dict:
    joints = [{"axes": list(tok)} for tok in spec.split(",")]
    return {"format": "kckf-session/1", "joints": joints, "sample_rate_hz": 100.0, **extra}


def sensors_text(robot: Robot, n: int = 30, rate_hz: float = 100.0) -> str:
    """A valid sensors.csv: ``t`` and the columns the robot needs (no unused gyro columns)."""
    header = ["t", *robot.used_gyro_columns, *robot.hall_names]
    lines = [",".join(header)]
    for k in range(n):
        cells = [repr(k / rate_hz)]
        cells += [f"{0.01 * (j + 1) + 0.001 * k:.6f}" for j in range(len(header) - 1)]
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def mocap_text(robot: Robot, t: np.ndarray, values: np.ndarray | None = None) -> str:
    if values is None:
        values = np.sin(np.outer(t, np.arange(1, robot.n_angles + 1)))
    lines = [",".join(["t", *robot.angle_names])]
    for tk, row in zip(t, values):
        cells = ["" if np.isnan(v) else repr(float(v)) for v in row]
        lines.append(",".join([repr(float(tk)), *cells]))
    return "\n".join(lines) + "\n"


def good_session(tmp_path, spec: str = SPEC, with_mocap: bool = True, **meta) -> str:
    robot = Robot.from_spec(spec)
    return write_files(
        tmp_path / "s",
        meta=meta_dict(spec, **meta),
        sensors=sensors_text(robot),
        mocap=mocap_text(robot, np.arange(36) / 120.0) if with_mocap else None,
    )


def edit(folder: str, name: str, change) -> str:
    """Rewrite ``folder/name`` as ``"\\n".join(change(lines))``; returns the file's path."""
    path = os.path.join(folder, name)
    with open(path) as f:
        lines = f.read().split("\n")
    with open(path, "w") as f:
        f.write("\n".join(change(lines)))
    return path


def set_cell(lines: list[str], line_no: int, column: str, value: str) -> list[str]:
    """Set one cell (``line_no`` counts from 1 = header)."""
    header = lines[0].split(",")
    cells = lines[line_no - 1].split(",")
    cells[header.index(column)] = value
    return lines[: line_no - 1] + [",".join(cells)] + lines[line_no:]


def random_session(rng, spec: str = SPEC, T: int = 200, F: int = 250) -> Session:
    robot = Robot.from_spec(spec)
    t = 1234.5 + np.cumsum(rng.uniform(0.005, 0.015, T))
    gyro = rng.normal(size=(T, 3 * robot.n_links))
    hall_v = rng.uniform(0.2, 2.5, size=(T, robot.n_hall))
    gyro[rng.random(gyro.shape) < 0.05] = np.nan
    hall_v[rng.random(hall_v.shape) < 0.05] = np.nan
    mocap_t = 1234.0 + np.arange(F) / 120.0
    mocap = 0.5 * rng.normal(size=(F, robot.n_angles))  # rad: within a joint's reach (120 deg)
    mocap[rng.random(mocap.shape) < 0.05] = np.nan
    return Session(
        robot=robot, t=t, gyro=gyro, hall_v=hall_v, sample_rate_hz=100.0,
        mocap_t=mocap_t, mocap=mocap, mocap_time_offset_s=0.25,
        hall_models={
            "hall1_x_l": {"a": 0.07, "b": 2.87, "c": 222000.0, "d": 8.43, "sign": 1, "unit": "deg"},
            "hall2_y_r": {"a": 0.001, "b": 3.0, "c": 4000.0, "d": 9.0, "sign": -1, "unit": "rad"},
        },
        description="round trip, with a comma, and \"quotes\"",
        extra_meta={"subject": "S01", "notes": {"trial": 3, "tags": ["a", "b"]}},
    )


# ---------------------------------------------------------------------- round trip


def test_round_trip(tmp_path):
    s = random_session(np.random.default_rng(0))
    write_session(s, tmp_path / "out")
    r = read_session(tmp_path / "out")
    assert r.robot == s.robot
    np.testing.assert_array_equal(r.t, s.t)  # bit-exact times
    np.testing.assert_array_equal(r.mocap_t, s.mocap_t)
    for name in ("gyro", "hall_v", "mocap"):
        a, b = getattr(r, name), getattr(s, name)
        assert a.dtype == np.float64 and a.shape == b.shape
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=0)
    assert r.sample_rate_hz == s.sample_rate_hz
    assert r.mocap_time_offset_s == s.mocap_time_offset_s
    assert r.hall_models == s.hall_models
    assert r.description == s.description
    assert r.extra_meta == s.extra_meta
    assert r.path == str(tmp_path / "out")

    # Writing what was read gives the same files.
    write_session(r, tmp_path / "again")
    for name in ("meta.json", "sensors.csv", "mocap.csv"):
        with open(tmp_path / "out" / name) as f1, open(tmp_path / "again" / name) as f2:
            assert f1.read() == f2.read(), name


def test_written_layout(tmp_path):
    s = random_session(np.random.default_rng(1), spec="x,y", T=5, F=6)
    s.gyro[2, 4] = np.nan
    write_session(s, tmp_path / "nested" / "out")  # creates parent folders
    folder = tmp_path / "nested" / "out"
    lines = (folder / "sensors.csv").read_text().splitlines()
    assert lines[0].split(",") == ["t", *s.robot.gyro_names, *s.robot.hall_names]
    assert lines[3].split(",")[1 + 4] == ""  # NaN is an empty cell
    assert float(lines[1].split(",")[0]) == s.t[0]
    mlines = (folder / "mocap.csv").read_text().splitlines()
    assert mlines[0].split(",") == ["t", *s.robot.angle_names]
    meta = json.loads((folder / "meta.json").read_text())
    assert list(meta)[:6] == [
        "format", "joints", "sample_rate_hz", "mocap_time_offset_s", "hall_models", "description",
    ]
    assert meta["format"] == "kckf-session/1" and meta["subject"] == "S01"
    assert (folder / "meta.json").read_text().startswith('{\n  "format"')  # indent 2


def test_write_without_mocap_removes_stale_mocap(tmp_path):
    s = random_session(np.random.default_rng(2), T=20, F=30)
    write_session(s, tmp_path / "out")
    bare = Session(s.robot, s.t, s.gyro, s.hall_v, sample_rate_hz=100.0)
    write_session(bare, tmp_path / "out")
    assert not (tmp_path / "out" / "mocap.csv").exists()
    r = read_session(tmp_path / "out")
    assert r.mocap is None and r.mocap_t is None and not r.has_truth


# ---------------------------------------------------------------------- hand-written files


def test_minimal_hand_written(tmp_path):
    folder = write_files(
        tmp_path / "s",
        meta='{"format": "kckf-session/1", "joints": [{"axes": ["x"]}, {"axes": ["y"]}],'
        ' "sample_rate_hz": 100}',
        # Free column order, an extra text column, no z gyro columns, missing cells.
        sensors=(
            "hall2_y_r,t,gyro1_x,gyro1_y,gyro2_x,gyro2_y,gyro3_x,gyro3_y,note,"
            "hall1_x_l,hall1_x_r,hall2_y_l\n"
            "1.4,0.00,0.1,0.2,0.3,0.4,0.5,0.6,start,1.1,1.2,1.3\n"
            "2.4,0.01,,NaN,nan,0.4,0.5,0.6,,2.1,2.2,2.3\n"
            "3.4,0.02,0.1,0.2,0.3,0.4,0.5,0.6,x y z,3.1,,3.3\n"
        ),
    )
    s = read_session(folder)
    robot = Robot.from_spec("x,y")
    assert s.robot == robot and s.sample_rate_hz == 100.0 and s.mocap_time_offset_s == 0.0
    assert s.hall_models == {} and s.description == "" and s.extra_meta == {}
    np.testing.assert_array_equal(s.t, [0.0, 0.01, 0.02])
    assert s.gyro.shape == (3, 9) and s.hall_v.shape == (3, 4)
    g = dict(zip(robot.gyro_names, s.gyro[0]))
    assert g["gyro1_x"] == 0.1 and g["gyro3_y"] == 0.6
    assert all(np.isnan(g[f"gyro{L}_z"]) for L in (1, 2, 3))  # optional columns absent
    g1 = dict(zip(robot.gyro_names, s.gyro[1]))
    assert np.isnan([g1["gyro1_x"], g1["gyro1_y"], g1["gyro2_x"]]).all() and g1["gyro2_y"] == 0.4
    np.testing.assert_array_equal(s.hall_v[0], [1.1, 1.2, 1.3, 1.4])
    assert np.isnan(s.hall_v[2, 1])
    np.testing.assert_allclose(s.dt(), [0.0, 0.01, 0.01])
    assert s.dt()[0] == 0.0 and s.n_steps == 3 and s.duration_s == 0.02
    assert not s.has_truth and s.truth().shape == (3, 4) and np.isnan(s.truth()).all()


def test_optional_gyro_z_present_is_read(tmp_path):
    robot = Robot.from_spec("x,y")
    text = sensors_text(robot, n=4).split("\n")
    text[0] += ",gyro2_z"
    text[1:5] = [line + ",0.5" for line in text[1:5]]
    s = read_session(write_files(tmp_path / "s", meta=meta_dict("x,y"), sensors="\n".join(text)))
    z = s.gyro[:, robot.gyro_names.index("gyro2_z")]
    np.testing.assert_array_equal(z, 0.5)
    assert np.isnan(s.gyro[:, robot.gyro_names.index("gyro1_z")]).all()


def test_unusual_but_valid_text_reads_the_same(tmp_path):
    """Quoted cells, CRLF, blank lines, a BOM, spaces and no final newline: the careful
    (cell-by-cell) reader agrees with the fast one."""
    plain = good_session(tmp_path)
    expected = read_session(plain)
    with open(os.path.join(plain, "sensors.csv")) as f:
        lines = f.read().split("\n")
    padded = [",".join(f" {c} " for c in line.split(",")) for line in lines[2:-1]]
    quoted = ",".join(f'"{c}"' for c in lines[1].split(","))
    for name, first in (("odd", quoted), ("odd_unquoted", lines[1])):
        text = "\r\n".join(["\ufeff" + lines[0], first, "", *padded])
        got = read_session(write_files(tmp_path / name, meta=meta_dict(), sensors=text))
        np.testing.assert_array_equal(got.t, expected.t)
        np.testing.assert_array_equal(got.gyro, expected.gyro)
        np.testing.assert_array_equal(got.hall_v, expected.hall_v)


def test_fast_path_reads_a_one_hour_session(tmp_path, monkeypatch):
    robot = Robot.from_spec(SPEC)
    header = ["t", *robot.gyro_names, *robot.hall_names]
    rest = ",".join("" if j % 7 == 3 else f"{0.123456789 * j:.9g}" for j in range(len(header) - 1))
    T = 360_000
    body = "\n".join([f"{k / 100.0!r},{rest}" for k in range(T)])
    folder = write_files(
        tmp_path / "big", meta=meta_dict(), sensors=",".join(header) + "\n" + body + "\n"
    )

    def no_slow_path(*args, **kwargs):
        raise AssertionError("a well-formed file should not need the cell-by-cell reader")

    monkeypatch.setattr(_csvio, "_parse_slow", no_slow_path)
    s = read_session(folder)
    assert s.gyro.shape == (T, 15) and s.hall_v.shape == (T, 8)
    assert s.t[-1] == (T - 1) / 100.0
    assert np.isnan(s.gyro[:, 3]).all() and s.gyro[5, 1] == pytest.approx(0.123456789)


# ---------------------------------------------------------------------- error messages


def test_missing_column(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: [
        ",".join(c for j, c in enumerate(line.split(",")) if j != 13) for line in L
    ])
    message = error_of(folder)
    assert message == (
        f"{folder}/sensors.csv: missing column 'hall2_y_l' "
        "(the robot in meta.json has joints x,y,x,y)"
    )


def test_text_in_a_number_cell(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: set_cell(L, 12, "gyro1_x", "abc"))
    message = error_of(folder)
    assert message == (
        f"{folder}/sensors.csv, line 12, column 'gyro1_x': expected a number "
        "(empty or nan for a missing reading), got 'abc'"
    )


@pytest.mark.parametrize("cell", ["inf", "-inf", "Infinity"])
def test_infinite_cell(tmp_path, cell):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: set_cell(L, 7, "hall3_x_r", cell))
    message = error_of(folder)
    assert message.startswith(f"{folder}/sensors.csv, line 7, column 'hall3_x_r': ")
    assert "finite" in message and message.endswith("inf")


def test_extra_cell_in_a_row(tmp_path):
    folder = good_session(tmp_path)
    # As the contract check does: "text in a number cell" by inserting a cell.
    edit(folder, "sensors.csv", lambda L: L[:9] + [L[9].replace(",", ",abc,", 1)] + L[10:])
    message = error_of(folder)
    assert message.startswith(f"{folder}/sensors.csv, line 10: ")
    assert "20 cells" in message and "expected 19" in message


def test_missing_cell_in_a_row(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: L[:4] + [L[4].rsplit(",", 1)[0]] + L[5:])
    assert error_of(folder).startswith(f"{folder}/sensors.csv, line 5: 18 cells, expected 19")


def test_non_increasing_t(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: L[:20] + [L[21], L[20]] + L[22:])
    message = error_of(folder)
    assert message == (
        f"{folder}/sensors.csv, line 22: t = 0.19 is not after the previous row's t = 0.2; "
        "t must be strictly increasing"
    )


def test_duplicate_t(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: set_cell(L, 6, "t", "0.03"))
    message = error_of(folder)
    assert message.startswith(f"{folder}/sensors.csv, line 6: t = 0.03 is not after")
    assert "t = 0.03;" in message


@pytest.mark.parametrize("cell", ["", "nan"])
def test_missing_t(tmp_path, cell):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: set_cell(L, 9, "t", cell))
    message = error_of(folder)
    assert message.startswith(f"{folder}/sensors.csv, line 9, column 't': t is missing")


def test_first_problem_is_reported(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: set_cell(set_cell(L, 9, "t", ""), 4, "gyro2_x", "inf"))
    assert ", line 4, column 'gyro2_x'" in error_of(folder)


def test_line_numbers_count_blank_lines(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: L[:3] + [""] + set_cell(L, 8, "hall1_x_l", "x")[3:])
    assert ", line 9, column 'hall1_x_l'" in error_of(folder)


def test_no_data_rows(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "sensors.csv", lambda L: L[:1])
    assert error_of(folder) == f"{folder}/sensors.csv: no data rows after the header line"


def test_broken_json(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "meta.json", lambda L: ['{"format": "kckf-session/1",', '  "joints": ['])
    message = error_of(folder)
    assert message.startswith(f"{folder}/meta.json, line 2, column ")
    assert "not valid JSON" in message


def test_wrong_format(tmp_path):
    folder = good_session(tmp_path, format="kckf-session/2")
    message = error_of(folder)
    assert message == (
        f"{folder}/meta.json: 'format' must be 'kckf-session/1', got 'kckf-session/2'"
    )


def test_unknown_axis(tmp_path):
    folder = good_session(tmp_path, joints=[{"axes": ["x"]}, {"axes": ["w"]}])
    message = error_of(folder)
    assert message.startswith(f"{folder}/meta.json: ") and "'w'" in message
    assert "joints[1]" in message


@pytest.mark.parametrize(
    ("meta", "expected"),
    [
        ({"sample_rate_hz": 0}, "'sample_rate_hz' must be a positive number (Hz), got 0"),
        ({"sample_rate_hz": "100"}, "'sample_rate_hz' must be a positive number (Hz), got '100'"),
        ({"mocap_time_offset_s": None}, "'mocap_time_offset_s' must be a number (s), got None"),
        ({"description": 3}, "'description' must be a string, got 3"),
        ({"hall_models": {"hall9_x_l": {}}}, "'hall9_x_l' is not a Hall sensor"),
        ({"hall_models": {"hall1_x_l": {"a": -1, "b": 1, "c": 1, "d": 1}}},
         "hall_models['hall1_x_l'].a: expected a positive number, got -1"),
    ],
)
def test_bad_meta_values(tmp_path, meta, expected):
    folder = good_session(tmp_path, **meta)
    message = error_of(folder)
    assert message.startswith(f"{folder}/meta.json: ") and expected in message


def test_missing_joints(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "meta.json", lambda L: ['{"format": "kckf-session/1", "sample_rate_hz": 100}'])
    message = error_of(folder)
    assert message.startswith(f"{folder}/meta.json: 'joints'")


def test_missing_files(tmp_path):
    assert error_of(tmp_path / "nope") == f"{tmp_path / 'nope'}: no such session folder"
    folder = good_session(tmp_path)
    os.remove(os.path.join(folder, "sensors.csv"))
    assert error_of(folder).startswith(f"{folder}/sensors.csv: file not found")
    os.remove(os.path.join(folder, "meta.json"))
    assert error_of(folder).startswith(f"{folder}/meta.json: file not found")


def test_require_mocap(tmp_path):
    folder = good_session(tmp_path, with_mocap=False)
    assert read_session(folder).mocap is None
    message = error_of(folder, require_mocap=True)
    assert message.startswith(f"{folder}/mocap.csv: file not found")


def test_no_mocap_overlap(tmp_path):
    robot = Robot.from_spec(SPEC)
    folder = write_files(
        tmp_path / "s",
        meta=meta_dict(mocap_time_offset_s=100.0),
        sensors=sensors_text(robot, n=6001),  # 0-60 s
        mocap=mocap_text(robot, np.linspace(0.0, 20.0, 11)),
    )
    message = error_of(folder)
    assert message == (
        f"{folder}/mocap.csv: no overlap with the sensors (mocap covers 100.0-120.0 s in "
        "sensor time, sensors 0.0-60.0 s); check mocap_time_offset_s in meta.json"
    )


def test_mocap_missing_column(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "mocap.csv", lambda L: [line.rsplit(",", 1)[0] for line in L])
    assert error_of(folder) == (
        f"{folder}/mocap.csv: missing column 'phi_y' (the robot in meta.json has joints x,y,x,y)"
    )


def test_mocap_bad_cells(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "mocap.csv", lambda L: L[:5] + [L[6], L[5]] + L[7:])
    assert error_of(folder).startswith(f"{folder}/mocap.csv, line 7: t = ")
    folder = good_session(tmp_path)
    edit(folder, "mocap.csv", lambda L: set_cell(L, 3, "theta2_y", "occluded"))
    assert error_of(folder).startswith(f"{folder}/mocap.csv, line 3, column 'theta2_y': ")


def test_mocap_empty_cells_are_missing_frames(tmp_path):
    folder = good_session(tmp_path)
    edit(folder, "mocap.csv", lambda L: set_cell(L, 3, "theta2_y", ""))
    s = read_session(folder)
    assert np.isnan(s.mocap[1, 1]) and np.isfinite(s.mocap[1, 0])
    assert s.has_truth


# ---------------------------------------------------------------------- Session validation


def test_session_validates_fields():
    robot = Robot.from_spec("x,y")
    t = np.arange(4) / 100.0
    ok = dict(robot=robot, t=t, gyro=np.zeros((4, 9)), hall_v=np.zeros((4, 4)),
              sample_rate_hz=100.0)
    s = Session(**ok)
    assert s.t.dtype == np.float64
    assert Session(**{**ok, "gyro": np.zeros((4, 9), dtype=np.float32)}).gyro.dtype == np.float64
    bad = [
        ({"gyro": np.zeros((4, 8))}, "Session.gyro: expected shape (4, 9), got (4, 8)"),
        ({"hall_v": np.zeros((3, 4))}, "Session.hall_v: expected shape (4, 4), got (3, 4)"),
        ({"t": np.zeros((4, 1))}, "Session.t: expected shape (T,), got (4, 1)"),
        ({"t": t[::-1]}, "Session.t: expected strictly increasing times"),
        ({"gyro": np.full((4, 9), "a")}, "Session.gyro: expected a real number array"),
        ({"hall_v": np.full((4, 4), np.inf)}, "Session.hall_v: expected finite values"),
        ({"sample_rate_hz": 0.0}, "Session.sample_rate_hz: expected a positive number"),
        ({"mocap_t": t}, "expected both arrays or both None"),
        ({"mocap_t": t, "mocap": np.zeros((4, 3))},
         "Session.mocap: expected shape (4, 4), got (4, 3)"),
        ({"extra_meta": {"joints": []}}, "Session.extra_meta: key 'joints'"),
        ({"hall_models": {"hallX": {}}}, "'hallX' is not a Hall sensor"),
    ]
    for change, expected in bad:
        with pytest.raises(ValueError) as info:
            Session(**{**ok, **change})
        assert expected in str(info.value), (change, str(info.value))


def test_dt_is_differenced_in_float64():
    robot = Robot.from_spec("x")
    t = 1.0e6 + np.array([0.0, 0.01, 0.03, 0.04])
    s = Session(robot, t, np.zeros((4, 6)), np.zeros((4, 2)), sample_rate_hz=100.0)
    dt = s.dt()
    assert dt.dtype == np.float64 and dt[0] == 0.0
    np.testing.assert_array_equal(dt[1:], np.diff(t))


# ---------------------------------------------------------------------- mocap alignment


def f_smooth(t):
    return np.stack([np.sin(2.0 * t), np.cos(3.0 * t) + 0.5 * t], axis=-1)


def test_align_120hz_onto_100hz():
    mocap_t = np.arange(0, 1200) / 120.0  # 0 .. 9.9917 s
    sensor_t = np.arange(0, 1010) / 100.0  # 0 .. 10.09 s
    values = f_smooth(mocap_t)
    got = align_mocap(sensor_t, mocap_t, values, 0.0)
    assert got.shape == (1010, 2) and got.dtype == np.float64
    inside = sensor_t <= mocap_t[-1]
    for k in range(2):
        expected = np.interp(sensor_t, mocap_t, values[:, k])
        np.testing.assert_allclose(got[inside, k], expected[inside], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[inside], f_smooth(sensor_t[inside]), atol=1e-4)
    assert np.isnan(got[~inside]).all() and (~inside).sum() == 10  # 10.00 .. 10.09 s


def test_align_offset_and_outside_span():
    mocap_t = np.arange(0, 241) / 120.0  # 2 s of mocap clock
    values = f_smooth(mocap_t)
    sensor_t = np.arange(0, 601) / 100.0  # 0 .. 6 s
    offset = 3.0  # mocap t = 0 is sensor t = 3
    got = align_mocap(sensor_t, mocap_t, values, offset)
    inside = (sensor_t >= 3.0) & (sensor_t <= 5.0)
    assert np.isnan(got[~inside]).all()
    np.testing.assert_allclose(got[inside], f_smooth(sensor_t[inside] - offset), atol=1e-4)
    assert got[300, 0] == values[0, 0] and got[500, 1] == values[-1, 1]  # the span's ends


def test_align_nan_frames_per_column():
    mocap_t = np.arange(0, 121) / 120.0
    values = f_smooth(mocap_t)
    values[[30, 31], 0] = np.nan  # two dropped frames in column 0 only: bridged
    values[60:80, 1] = np.nan  # a long occlusion in column 1: no truth inside it
    sensor_t = np.arange(0, 101) / 100.0
    got = align_mocap(sensor_t, mocap_t, values, 0.0)
    assert np.isfinite(got[:, 0]).all()
    valid = np.isfinite(values[:, 0])
    np.testing.assert_allclose(
        got[:, 0], np.interp(sensor_t, mocap_t[valid], values[valid, 0]), atol=1e-15
    )
    gap = (sensor_t > mocap_t[59]) & (sensor_t < mocap_t[80])
    assert np.isnan(got[gap, 1]).all() and np.isfinite(got[~gap, 1]).all()
    np.testing.assert_allclose(got[~gap, 1], f_smooth(sensor_t[~gap])[:, 1], atol=1e-4)


def test_align_max_gap():
    mocap_t = np.arange(10) * 0.1
    values = np.arange(10.0)[:, None]
    values[3:5] = np.nan  # valid frames 0.2 and 0.5: a 0.3 s gap
    sensor_t = np.array([0.2, 0.25, 0.35, 0.45, 0.5, 0.55])
    default = align_mocap(sensor_t, mocap_t, values, 0.0)  # max gap 3 x 0.1 s: bridged
    np.testing.assert_allclose(default[:, 0], [2.0, 2.5, 3.5, 4.5, 5.0, 5.5])
    strict = align_mocap(sensor_t, mocap_t, values, 0.0, max_gap_s=0.25)
    np.testing.assert_array_equal(np.isnan(strict[:, 0]), [False, True, True, True, False, False])
    values[5] = np.nan  # now 0.2 .. 0.6 = 4 frame intervals: longer than the default
    longer = align_mocap(sensor_t, mocap_t, values, 0.0)
    np.testing.assert_array_equal(np.isnan(longer[:, 0]), [False, True, True, True, True, True])


def test_align_edge_cases():
    sensor_t = np.array([0.0, 1.0, 2.0])
    one = align_mocap(sensor_t, np.array([1.0]), np.array([[7.0]]), 0.0)
    np.testing.assert_array_equal(np.isnan(one[:, 0]), [True, False, True])
    assert one[1, 0] == 7.0
    none = align_mocap(sensor_t, np.array([0.0, 2.0]), np.full((2, 1), np.nan), 0.0)
    assert np.isnan(none).all()
    flat = align_mocap(sensor_t, np.array([0.0, 2.0]), np.array([0.0, 4.0]), 0.0)
    assert flat.shape == (3,) and flat.tolist() == [0.0, 2.0, 4.0]
    with pytest.raises(ValueError, match="mocap must have shape"):
        align_mocap(sensor_t, np.array([0.0, 2.0]), np.zeros((3, 1)), 0.0)


def test_session_truth_uses_offset_and_is_cached(tmp_path):
    robot = Robot.from_spec(SPEC)
    mocap_t = np.arange(0, 60) / 120.0  # mocap clock 0 .. 0.49 s
    values = np.column_stack([np.sin(mocap_t * (k + 1)) for k in range(robot.n_angles)])
    folder = write_files(
        tmp_path / "s",
        meta=meta_dict(mocap_time_offset_s=-0.1),  # sensor time = mocap t - 0.1
        sensors=sensors_text(robot, n=50),  # 0 .. 0.49 s
        mocap=mocap_text(robot, mocap_t, values),
    )
    s = read_session(folder)
    truth = s.truth()
    assert truth is s.truth() and truth.shape == (50, robot.n_angles) and s.has_truth
    expected = align_mocap(s.t, mocap_t, values, -0.1)
    np.testing.assert_array_equal(truth, expected)
    inside = s.t <= mocap_t[-1] - 0.1
    assert np.isnan(truth[~inside]).all() and np.isfinite(truth[inside]).all()
    np.testing.assert_allclose(truth[inside, 2], np.sin((s.t[inside] + 0.1) * 3), atol=1e-4)


def test_message_helpers():
    # ``_s`` prints seconds with a decimal point for the overlap message.
    assert _session._s(100) == "100.0" and _session._s(0.05) == "0.05"
    assert math.isnan(_csvio._cell("  "))
