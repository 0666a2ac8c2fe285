"""The other containers of a session (OpenSim Storage motion capture, XDF recordings): each
read into the same ``Session`` as the CSV folder, and each mistake refused in one line."""

from __future__ import annotations

import json
import os
import shutil
import sys

import numpy as np
import pytest
from helpers import error_of
from xdf_writer import XdfStream, chunk, write_xdf

from kckf_jax import Robot, Session, read_session, simulate, write_session
from kckf_jax.cli import main

DEG = 180.0 / np.pi
T0 = 4711.25  # the LSL clock at the first sensor sample (seconds since the recorder's boot)
C = -1234.5  # the motion-capture machine's clock + C = the recorder's clock
THEIRS = {"theta1_x": "lumbar_bending", "theta2_y": "lumbar_extension", "theta3_x": "l2_bend",
          "theta4_y": "l2_ext", "phi_x": "torso_list", "phi_y": "torso_tilt"}


def meta_of(folder) -> dict:
    with open(os.path.join(folder, "meta.json")) as f:
        return json.load(f)


def write_meta(folder, meta: dict) -> None:
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "meta.json"), "w") as f:
        json.dump(meta, f)


def sensor_stream(s: Session, names=None, **kw) -> XdfStream:
    """``s``'s sensors as a double64 stream stamped ``t + T0`` (columns ``names``, default all,
    in reverse order: the order of channels is free)."""
    names = list(names or (*s.robot.gyro_names, *s.robot.hall_names))[::-1]
    cols = {**dict(zip(s.robot.gyro_names, s.gyro.T)), **dict(zip(s.robot.hall_names, s.hall_v.T))}
    units = ["rad/s" if n.startswith("gyro") else "V" for n in names]
    return XdfStream(**{"name": "exoshell", "labels": names, "units": units, "stamps": s.t + T0,
                        "values": np.stack([cols[n] for n in names], axis=1), "srate": 100.0,
                        "type": "IMU", "clock_offsets": [(T0 + k, 0.0) for k in range(3)],
                        **kw})


def mocap_stream(s: Session, labels=None, unit: str = "deg", **kw) -> XdfStream:
    """``s``'s motion capture, in degrees, stamped on the mocap machine's clock (``- C``)."""
    return XdfStream(**{
        "name": "vicon", "labels": list(labels or s.robot.angle_names),
        "units": [unit] * s.robot.n_angles, "stamps": s.mocap_t + s.mocap_time_offset_s + T0 - C,
        "values": s.mocap * (DEG if unit == "deg" else 1.0), "srate": 120.0, "type": "MoCap",
        "clock_offsets": [(T0 - C + k, C) for k in range(3)], **kw})


def write_mot(path, time, columns: dict, in_degrees: str | None = "yes") -> None:
    """An OpenSim Storage file as inverse kinematics writes it (tab separated)."""
    head = ["Coordinates", "version=1", f"nRows={len(time)}", f"nColumns={len(columns) + 1}"]
    head += [f"inDegrees={in_degrees}"] if in_degrees is not None else []
    head += ["", "Units are S.I. units (second, meters, Newtons, ...)",
             "If the header above contains a line with 'inDegrees', this indicates whether "
             "rotational values are in degrees (yes) or radians (no).", "", "endheader",
             "\t".join(["time", *columns])]
    rows = np.column_stack([time, *columns.values()])
    lines = ["\t".join(f"{v!r:>20}" for v in row.tolist()) for row in rows]
    with open(path, "w") as f:
        f.write("\n".join(head + lines) + "\n")


def small_session(spec: str = "x,y", n: int = 120) -> Session:
    robot = Robot.from_spec(spec)
    t = np.arange(n) / 100.0
    k = np.arange(1, 1 + 3 * robot.n_links)
    gyro = 0.1 * np.sin(np.outer(t, k))
    hall_v = 1.5 + 0.1 * np.cos(np.outer(t, np.arange(1, 1 + robot.n_hall)))
    mocap_t = np.arange(0.001, t[-1], 1 / 120)
    mocap = 0.2 * np.sin(np.outer(mocap_t, np.arange(1, 1 + robot.n_angles)))
    return Session(robot, t, gyro, hall_v, 100.0, mocap_t, mocap)


def xdf_folder(folder, s: Session, streams, **meta) -> str:
    """A session folder holding ``meta.json`` (of ``s``, offset 0) and ``recording.xdf``."""
    write_session(s, folder)
    os.remove(os.path.join(folder, "sensors.csv"))
    if os.path.exists(os.path.join(folder, "mocap.csv")):
        os.remove(os.path.join(folder, "mocap.csv"))
    write_meta(folder, {**meta_of(folder), "mocap_time_offset_s": 0.0, **meta})
    write_xdf(os.path.join(folder, "recording.xdf"), streams)
    return str(folder)


# ---------------------------------------------------------------------- the writer


def test_the_writer_reads_back_through_pyxdf_exactly(tmp_path, rng):
    import pyxdf

    t = 100.0 + np.arange(230) / 100.0  # most stamps are the previous + 1/srate: left out
    t[50:] += 0.0013  # a jump: the stamp is written again
    v = rng.standard_normal((230, 3))
    v[5, 1] = np.nan
    streams = [
        XdfStream("a", ["x", "y", "z"], t, v, srate=100.0, deduce_stamps=True, chunk=64,
                  units=["rad/s", "V", ""]),
        XdfStream("b", ["p"], 100 + np.sort(rng.uniform(0, 2, 30)),
                  rng.standard_normal((30, 1)).astype(np.float32), fmt="float32",
                  clock_offsets=[(100.0, 0.25), (105.0, 0.5)]),
        XdfStream("c", ["n1", "n2"], np.array([100.5, 101.0]),
                  np.array([[1, -2], [300, 4]], dtype=np.int16), fmt="int16"),
        XdfStream("markers", ["marker"], np.array([100.5, 101.0]), [["go"], ["stop"]],
                  fmt="string"),
    ]
    path = tmp_path / "r.xdf"
    write_xdf(path, streams)
    got, header = pyxdf.load_xdf(str(path), synchronize_clocks=False, dejitter_timestamps=False)
    assert header["info"]["version"] == ["1.0"]
    for g, s in zip(got, streams):
        info = g["info"]
        assert info["name"] == [s.name] and info["channel_format"] == [s.fmt]
        channels = info["desc"][0]["channels"][0]["channel"]
        assert [c["label"][0] for c in channels] == list(s.labels)
        np.testing.assert_array_equal(g["time_stamps"], s.stamps)
        if s.fmt == "string":
            assert g["time_series"] == s.values
        else:
            assert g["time_series"].dtype == np.asarray(s.values).dtype
            np.testing.assert_array_equal(g["time_series"], s.values)
        assert g["clock_times"] == [w for w, _ in s.clock_offsets]
        assert g["clock_values"] == [o for _, o in s.clock_offsets]
        assert g["footer"]["info"]["sample_count"] == [str(len(s.stamps))]
    assert channels and got[0]["info"]["desc"][0]["channels"][0]["channel"][0]["unit"] == ["rad/s"]


# ---------------------------------------------------------------------- one session, three ways


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    """One simulated session as a CSV folder, as an XDF recording (sensors and mocap streams
    among two others, mocap in degrees on another machine's clock) and with its mocap as an
    OpenSim ``.mot`` in degrees under other names (``mocap_columns``)."""
    base = tmp_path_factory.mktemp("containers")
    sim = simulate("x,y,x,y", "cyclic", seed=3, duration_s=6.0, drop_prob=0.01)
    write_session(sim, base / "csv")
    ref = read_session(base / "csv")
    eeg = XdfStream("EEG", ["Fp1", "Fp2", "Cz"], T0 + np.arange(1500) / 250.0,
                    np.zeros((1500, 3), np.float32), fmt="float32", srate=250.0)
    markers = XdfStream("Markers", ["marker"], np.array([T0 + 1.0]), [["start"]], fmt="string")
    xdf = xdf_folder(base / "xdf", ref, [eeg, sensor_stream(ref), markers, mocap_stream(ref)])

    mot = base / "mot"
    shutil.copytree(base / "csv", mot)
    os.remove(mot / "mocap.csv")
    write_meta(mot, {**meta_of(mot), "mocap_columns": THEIRS})
    columns = {"pelvis_tx": np.zeros(ref.mocap_t.shape)}  # not ours: ignored
    for name in reversed(ref.robot.angle_names):
        columns[THEIRS[name]] = ref.mocap[:, ref.robot.angle_names.index(name)] * DEG
    write_mot(mot / "mocap.mot", ref.mocap_t, columns)
    return {"csv": str(base / "csv"), "xdf": xdf, "mot": str(mot), "ref": ref}


def test_xdf_gives_the_csv_sessions_arrays(three):
    ref, s = three["ref"], read_session(three["xdf"], require_mocap=True)
    assert (s.sensors_file, s.mocap_file, s.path) == ("recording.xdf", "recording.xdf",
                                                      three["xdf"])
    np.testing.assert_allclose(s.t, ref.t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(s.gyro, ref.gyro)  # double64: exact, NaN where NaN
    np.testing.assert_array_equal(s.hall_v, ref.hall_v)
    assert s.mocap_time_offset_s == 0.0
    np.testing.assert_allclose(s.mocap_t, ref.mocap_t + ref.mocap_time_offset_s, atol=1e-9)
    np.testing.assert_allclose(s.mocap, ref.mocap, rtol=1e-12, atol=1e-15)  # deg -> rad
    np.testing.assert_allclose(s.truth(), ref.truth(), rtol=0, atol=1e-9)  # rad; NaN alike


def test_storage_gives_the_csv_sessions_arrays(three):
    ref, s = three["ref"], read_session(three["mot"], require_mocap=True)
    assert (s.sensors_file, s.mocap_file) == ("sensors.csv", "mocap.mot")
    for name in ("t", "gyro", "hall_v", "mocap_t"):
        np.testing.assert_array_equal(getattr(s, name), getattr(ref, name))
    assert s.mocap_time_offset_s == ref.mocap_time_offset_s
    np.testing.assert_allclose(s.mocap, ref.mocap, rtol=1e-12, atol=1e-15)
    assert s.extra_meta["mocap_columns"] == THEIRS


def test_evaluate_gives_the_same_rmse_from_every_container(three, capsys):
    rmse = {}
    for kind in ("csv", "xdf", "mot"):
        assert main(["evaluate", three[kind], "--method", "kckf", "--json"]) == 0
        rmse[kind] = json.loads(capsys.readouterr().out)["methods"]["kckf"]["rmse_deg"]
    assert set(rmse["csv"]) == set(three["ref"].robot.angle_names)
    for kind in ("xdf", "mot"):
        for name, value in rmse["csv"].items():
            assert rmse[kind][name] == pytest.approx(value, rel=1e-3), (kind, name)


def test_write_session_keeps_how_to_read_the_files(three, tmp_path):
    s = read_session(three["mot"])
    write_session(s, tmp_path / "out")  # our names in mocap.csv; mocap_columns kept
    back = read_session(tmp_path / "out")
    assert meta_of(tmp_path / "out")["mocap_columns"] == THEIRS
    assert back.mocap_file == "mocap.csv"
    np.testing.assert_allclose(back.mocap, s.mocap, rtol=1e-8)


# ---------------------------------------------------------------------- choosing streams


def test_mocap_columns_apply_to_mocap_csv_too(tmp_path):
    s = small_session()
    write_session(s, tmp_path / "s")
    path = tmp_path / "s" / "mocap.csv"
    path.write_text(path.read_text().replace("theta1_x", "hip", 1))
    assert error_of(tmp_path / "s") == (  # as before mocap_columns
        f"{path}: missing column 'theta1_x' (the robot in meta.json has joints x,y)")
    write_meta(tmp_path / "s", {**meta_of(tmp_path / "s"), "mocap_columns": {"theta1_x": "hip"}})
    np.testing.assert_allclose(read_session(tmp_path / "s").mocap, s.mocap, rtol=1e-8)
    write_meta(tmp_path / "s", {**meta_of(tmp_path / "s"), "mocap_columns": {"theta9_x": "a"}})
    assert "'mocap_columns' maps 'theta9_x', which is not an angle" in error_of(tmp_path / "s")


def test_xdf_streams_picks_among_matching_streams(tmp_path):
    s = small_session()
    twins = [sensor_stream(s), sensor_stream(s, name="exoshell-backup"), mocap_stream(s)]
    folder = xdf_folder(tmp_path / "a", s, twins)
    message = error_of(folder)
    assert message.startswith(f"{folder}/recording.xdf: 2 streams hold the sensors "
                              "('exoshell', 'exoshell-backup'); name one in meta.json")
    assert '"xdf_streams": {"sensors": "<stream name>"}' in message
    folder = xdf_folder(tmp_path / "b", s, twins, xdf_streams={"sensors": "exoshell-backup"})
    got = read_session(folder)
    np.testing.assert_array_equal(got.hall_v, s.hall_v)
    folder = xdf_folder(tmp_path / "c", s, twins, xdf_streams={"sensors": "imu"})
    assert error_of(folder).startswith(f"{folder}/recording.xdf: no stream named 'imu' "
                                       "(meta.json's xdf_streams.sensors); the streams: ")


def test_xdf_without_mocap_unused_gyros_and_a_mocap_file_beside(tmp_path):
    s = small_session()
    used = (*s.robot.used_gyro_columns, *s.robot.hall_names)  # no z rates in the stream
    folder = xdf_folder(tmp_path / "s", s, [sensor_stream(s, names=used)])
    got = read_session(folder)
    assert got.mocap is None and got.mocap_file == "mocap.csv"
    z = [s.robot.gyro_names.index(n) for n in s.robot.gyro_names if n.endswith("_z")]
    assert np.isnan(got.gyro[:, z]).all()
    assert "or a stream of recording.xdf" in error_of(folder, require_mocap=True)
    # The mocap from its own file, on its own clock (the offset applies to it).
    write_mot(os.path.join(folder, "mocap.sto"), s.mocap_t - 0.5, dict(
        zip(s.robot.angle_names, s.mocap.T)), in_degrees="no")
    write_meta(folder, {**meta_of(folder), "mocap_time_offset_s": 0.5})
    got = read_session(folder)
    assert got.mocap_file == "mocap.sto" and got.mocap_time_offset_s == 0.5
    np.testing.assert_allclose(got.truth(), s.truth(), atol=1e-12)


def test_pyxdf_missing_is_named_with_its_install(tmp_path, monkeypatch):
    s = small_session()
    folder = xdf_folder(tmp_path / "s", s, [sensor_stream(s)])
    monkeypatch.setitem(sys.modules, "pyxdf", None)  # import pyxdf raises ImportError
    assert error_of(folder) == (f"{folder}/recording.xdf: reading XDF needs pyxdf: pip install "
                                "'kckf-jax[lab]'")


# ---------------------------------------------------------------------- one-line refusals


def test_no_stream_matches(tmp_path):
    s = small_session()
    eeg = XdfStream("EEG", ["Fp1", "Fp2", "Cz", "Pz"], T0 + np.arange(10) / 250, np.zeros((10, 4)))
    folder = xdf_folder(tmp_path / "s", s, [eeg])
    message = error_of(folder)
    assert message.startswith(f"{folder}/recording.xdf: no stream holds the sensors (channel "
                              "labels 'gyro1_x', 'gyro1_y', 'gyro2_x' and 7 more")
    assert message.endswith("the streams: 'EEG' (4 channels: 'Fp1', 'Fp2', 'Cz' and 1 more)")


def test_a_label_missing_from_the_best_matching_stream(tmp_path):
    s = small_session()
    names = [n for n in (*s.robot.used_gyro_columns, *s.robot.hall_names) if n != "hall2_y_r"]
    folder = xdf_folder(tmp_path / "s", s, [sensor_stream(s, names=names)])
    assert error_of(folder).startswith(f"{folder}/recording.xdf, stream 'exoshell': no channel "
                                       "labelled 'hall2_y_r'; its labels: ")
    labels = ["theta1_x", "theta2_y", "phi_x", "tilt"]  # phi_y under a name nobody gave
    folder = xdf_folder(tmp_path / "m", s, [sensor_stream(s), mocap_stream(s, labels)])
    message = error_of(folder)
    assert message.startswith(f"{folder}/recording.xdf, stream 'vicon': no column 'phi_y' and "
                              "meta.json's mocap_columns names no other column for it")
    assert "it has 'theta1_x', 'theta2_y', 'phi_x', 'tilt'; map each" in message


def test_a_label_that_matches_nothing_in_a_storage_file(tmp_path):
    s = small_session()
    write_session(s, tmp_path / "s")
    os.remove(tmp_path / "s" / "mocap.csv")
    cols = dict(zip(["theta1_x", "theta2_y", "phi_x", "tilt"], s.mocap.T))
    write_mot(tmp_path / "s" / "mocap.mot", s.mocap_t, cols)
    write_meta(tmp_path / "s", {**meta_of(tmp_path / "s"), "mocap_columns": {"phi_y": "pitch"}})
    assert error_of(tmp_path / "s") == (
        f"{tmp_path}/s/mocap.mot: no column 'phi_y' nor 'pitch' (its name in meta.json's "
        "mocap_columns) (the robot in meta.json has joints x,y); it has 'time', 'theta1_x', "
        "'theta2_y', 'phi_x', 'tilt'; map each of our angles to its column in mocap_columns, e.g. "
        '"mocap_columns": {"phi_y": "<column>"}')


def test_storage_header_and_cells(tmp_path):
    s = small_session()
    write_session(s, tmp_path / "s")
    os.remove(tmp_path / "s" / "mocap.csv")
    mot = tmp_path / "s" / "mocap.mot"
    cols = dict(zip(s.robot.angle_names, s.mocap.T * DEG))
    write_mot(mot, s.mocap_t, cols, in_degrees=None)
    assert error_of(tmp_path / "s") == (
        f"{mot}: no 'inDegrees=yes' or 'inDegrees=no' line before 'endheader', so the angles' "
        "unit is unknown; add the one that is true to the header (OpenSim's inverse "
        "kinematics writes inDegrees=yes)")
    write_mot(mot, s.mocap_t, cols)
    text = mot.read_text()
    lines = text.split("\n")
    lines[13] = lines[13].replace(lines[13].split()[2], "abc")  # line 14: the 3rd frame
    mot.write_text("\n".join(lines))
    assert error_of(tmp_path / "s") == (
        f"{mot}, line 14, column 'theta2_y': expected a number (NaN for a missing frame), "
        "got 'abc'")
    mot.write_text(text.replace("endheader", "end"))
    assert error_of(tmp_path / "s").startswith(f"{mot}: no 'endheader' line")
    mot.write_text(text.replace("\ntime\t", "\nt\t"))
    assert error_of(tmp_path / "s") == (
        f"{mot}, line 11: the first column is 't', expected 'time' (s), as OpenSim writes it")
    mot.write_text(text.replace("inDegrees=yes", "inDegrees=no"))  # degrees said to be rad
    assert error_of(tmp_path / "s").startswith(f"{mot}, column 'theta1_x': |angle| reaches ")
    shutil.copy(mot, tmp_path / "s" / "mocap.sto")
    assert error_of(tmp_path / "s") == (
        f"{tmp_path}/s: 2 motion-capture files (mocap.mot, mocap.sto); a session holds one: "
        "move the others out of the folder")


def test_both_sensors_csv_and_recording_xdf(tmp_path):
    s = small_session()
    folder = xdf_folder(tmp_path / "s", s, [sensor_stream(s)])
    write_session(s, tmp_path / "csv")
    shutil.copy(tmp_path / "csv" / "sensors.csv", folder)
    assert error_of(folder) == (
        f"{folder}: both sensors.csv and recording.xdf; a session holds its sensors in one of "
        "them: move the other out of the folder")


def test_xdf_refusals(tmp_path):
    s = small_session()
    folder = xdf_folder(tmp_path / "u", s, [sensor_stream(s), mocap_stream(s, unit="furlong")])
    assert error_of(folder) == (
        f"{folder}/recording.xdf, stream 'vicon', channel 'theta1_x': unit 'furlong', expected "
        "one of rad, radian, radians, deg, degree, degrees (no unit means rad)")
    folder = xdf_folder(tmp_path / "o", s, [sensor_stream(s), mocap_stream(s)],
                        mocap_time_offset_s=0.25)
    assert error_of(folder) == (
        f"{folder}/meta.json: 'mocap_time_offset_s' is 0.25, but recording.xdf's streams share "
        "the LSL clock and no offset applies; set it to 0 or remove it")
    stamps = s.t + T0
    stamps[7] = stamps[6]
    folder = xdf_folder(tmp_path / "t", s, [sensor_stream(s, stamps=stamps)])
    assert error_of(folder) == (
        f"{folder}/recording.xdf, stream 'exoshell', sample 8: time stamp "
        f"{float(stamps[7])!r} is not after the previous sample's {float(stamps[6])!r}; time "
        "stamps must be strictly increasing")
    folder = xdf_folder(tmp_path / "n", s, [])
    with open(os.path.join(folder, "recording.xdf"), "wb") as f:
        f.write(b"t,gyro1_x\n0,1\n")
    assert error_of(folder) == (
        f"{folder}/recording.xdf: not an XDF file (it starts with b't,gy', an XDF file with "
        "b'XDF:')")
    with open(os.path.join(folder, "recording.xdf"), "wb") as f:  # a whole chunk, bad XML
        f.write(b"XDF:" + chunk(2, b"\x01\x00\x00\x00<info><name>broken"))
    assert error_of(folder).startswith(f"{folder}/recording.xdf: not a readable XDF file (")
    with open(os.path.join(folder, "recording.xdf"), "wb") as f:  # the chunk cut short
        f.write(b"XDF:\x01\x20\x02\x00\x01\x00\x00\x00<info><name>broken")
    assert error_of(folder) == (
        f"{folder}/recording.xdf: cut short at byte 30 (inside a stream header of stream id 1; "
        "the whole chunks end at byte 4), before the sensors' stream and its samples: nothing "
        "usable remains (the whole chunks hold the streams: none)")


def test_our_own_estimates_recorded_alongside_are_not_motion_capture(tmp_path):
    """LabRecorder recording the sensors, the mocap and ``kckf stream --sink lsl://``'s
    outlet (the angles' labels, source id ``kckf-...``): the mocap stream is the mocap; with
    no mocap stream, the session has none (not our estimates)."""
    s = small_session()
    ours = mocap_stream(s, name="kckf-exoshell-angles")
    folder = xdf_folder(tmp_path / "a", s, [sensor_stream(s), ours, mocap_stream(s)])
    got = read_session(folder)
    np.testing.assert_allclose(got.mocap, s.mocap, rtol=1e-12, atol=1e-12)
    folder = xdf_folder(tmp_path / "b", s, [sensor_stream(s), ours])
    assert read_session(folder).mocap is None
