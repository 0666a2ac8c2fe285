"""The Lab Streaming Layer source and sink (``lsl://``), kept on this machine.

LSL resolves streams by multicast and broadcast on the local network unless its configuration
says otherwise, and liblsl reads that configuration (the file ``LSLAPICFG`` names) once, when
it is first used. So this module never imports pylsl at collection: its fixture writes the
loopback configuration and sets ``LSLAPICFG`` first, then imports pylsl (../shared/notes/
lsl-loopback.md). Every outlet here lives in this process, under that configuration.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
import time
import uuid
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from kckf_jax import (
    PacketParser,
    Params,
    Robot,
    SensorSeries,
    StreamingFilter,
    run_filter,
    simulate,
)
from kckf_jax._stream import LslSink, LslSource, lsl_loopback_config, run_stream

if importlib.util.find_spec("pylsl") is None:  # without importing it: LSLAPICFG is not set yet
    pytest.skip("pylsl is not installed (pip install 'kckf-jax[lab]')", allow_module_level=True)

ROBOT = Robot.from_spec("x,y,x,y")
#: The columns an exoshell would publish: the used gyros and the Hall sensors (no z gyros).
COLUMNS = ROBOT.used_gyro_columns + ROBOT.hall_names


@pytest.fixture(scope="module", autouse=True)
def lsl(tmp_path_factory):
    """pylsl, with LSL on this machine only: ``LSLAPICFG`` set before pylsl is imported."""
    if "pylsl" in sys.modules and os.environ.get("LSLAPICFG") is None:
        pytest.fail("pylsl was imported in this worker before LSLAPICFG was set: LSL may have "
                    "read its default (network) configuration; import it only in tests that "
                    "set the loopback configuration first")
    cfg = lsl_loopback_config(tmp_path_factory.mktemp("lsl") / "lsl_api.cfg")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LSLAPICFG", cfg)
        yield pytest.importorskip("pylsl")


def unique(stem: str = "kckf-test") -> str:
    return f"{stem}-{uuid.uuid4().hex[:10]}"


def sensor_outlet(lsl, name: str, labels, source_id: str, fmt=None, units=None):
    info = lsl.StreamInfo(name, "Sensors", len(labels), lsl.IRREGULAR_RATE,
                          lsl.cf_double64 if fmt is None else fmt, source_id)
    channels = info.desc().append_child("channels")
    for label in labels:
        ch = channels.append_child("channel")
        ch.append_child_value("label", label)
        if units and label in units:
            ch.append_child_value("unit", units[label])
    return lsl.StreamOutlet(info)


class ListSink:
    def __init__(self):
        self.records = []

    def write(self, rec: dict) -> None:
        self.records.append(rec)

    def close(self) -> None:
        pass


def test_loopback_config_is_the_notes(tmp_path):
    text = Path(lsl_loopback_config(tmp_path / "x.cfg")).read_text()
    for line in ("ResolveScope = machine", "MachineAddresses = {127.0.0.1}",
                 "KnownPeers = {127.0.0.1}", "IPv6 = disable"):
        assert line in text


def test_lsl_source_through_run_stream_equals_batch(lsl):
    """An outlet of a session's sensor rows (channels in another order, the z gyros absent, an
    extra channel, the Hall sensors in mV) through ``LslSource`` and ``run_stream``: every
    sample is a packet, ``t`` its LSL stamp, and the estimates are the batch filter's over the
    same rows."""
    s = simulate(ROBOT, "cyclic", seed=5, duration_s=5.0, drop_prob=0.02)
    params = Params.paper_defaults(ROBOT, s.hall_models, dtype=jnp.float32)
    sf = StreamingFilter(params, "kckf")
    sf.warmup()  # compiled before the source is opened, as ``kckf stream`` does

    labels = ["battery_v"] + list(reversed(COLUMNS))
    values = {n: s.gyro[:, i] for i, n in enumerate(ROBOT.gyro_names)}
    values |= {n: 1000.0 * s.hall_v[:, i] for i, n in enumerate(ROBOT.hall_names)}
    values["battery_v"] = np.full(s.n_steps, 3.7)
    rows = np.stack([values[n] for n in labels], axis=1)
    t = 1000.0 + s.t  # LSL takes a stamp of 0.0 for "now"

    name = unique()
    units = dict.fromkeys(ROBOT.hall_names, "mV") | dict.fromkeys(ROBOT.gyro_names, "rad/s")
    outlet = sensor_outlet(lsl, name, labels, unique("exo"), units=units)
    source = LslSource(name, ROBOT, resolve_timeout=5.0, settle_s=0.0)
    source.open()
    assert outlet.wait_for_consumers(5.0)
    for row, ti in zip(rows, t):
        outlet.push_sample(row.tolist(), timestamp=float(ti))
    sink = ListSink()
    counts = run_stream(source, sink, sf, PacketParser(ROBOT), max_packets=s.n_steps,
                        idle_timeout=5.0)
    source.close()
    assert counts["packets"] == s.n_steps == source.n_read == len(sink.records)
    assert counts.get("ok", 0) + counts.get("masked", 0) == s.n_steps, counts
    np.testing.assert_array_equal([r["t"] for r in sink.records], t)

    gyro = s.gyro.copy()
    gyro[:, [i for i, n in enumerate(ROBOT.gyro_names) if n not in COLUMNS]] = np.nan
    series = SensorSeries(jnp.asarray(np.diff(t, prepend=t[0]), jnp.float32),
                          jnp.asarray(gyro, jnp.float32), jnp.asarray(s.hall_v, jnp.float32))
    ref = np.asarray(run_filter(params, series, "kckf")[1].angles, np.float64)
    got = np.array([[r.get(n, np.nan) for n in ROBOT.angle_names] for r in sink.records])
    np.testing.assert_allclose(got, ref, atol=1e-4, rtol=0)


def _pull(inlet, n: int, timeout: float = 5.0):
    samples, stamps = [], []
    deadline = time.monotonic() + timeout
    while len(samples) < n and time.monotonic() < deadline:
        x, ts = inlet.pull_sample(0.1)
        if ts is not None:
            samples.append(x)
            stamps.append(ts)
    return samples, stamps


def test_lsl_sink_read_back(lsl):
    name = unique()
    sink = LslSink(name, ROBOT)
    inlets = []
    for stream in (name, f"{name}-status"):
        (info,) = lsl.resolve_byprop("name", stream, minimum=1, timeout=5.0)
        inlet = lsl.StreamInlet(info, processing_flags=0)
        inlet.open_stream(5.0)
        inlets.append(inlet)
    angles_in, status_in = inlets
    full = angles_in.info(5.0)
    assert (full.type(), full.source_id()) == ("Angles", f"kckf-{name}")
    assert [full.desc().child("channels").child("channel").child_value(k)
            for k in ("label", "unit", "type")] == [ROBOT.angle_names[0], "rad", "angle"]

    K = len(ROBOT.angle_names)
    a = {n: 0.1 * (k + 1) for k, n in enumerate(ROBOT.angle_names)}
    records = [
        {"t": 0.0, **a, "status": "ok"},  # sent as 5e-324: LSL takes 0.0 for "now"
        {"t": 12.5, **a, "status": "masked", "note": "treated as missing: hall1_x_l"},
        {"t": 12.51, **{n: v for n, v in a.items() if n != "phi_y"}, "status": "ok"},
        {"t": None, "status": "malformed", "note": "not a UTF-8 JSON object"},
        {"t": 12.0, "status": "out_of_order", "note": "t = 12.0 is not after 12.51"},
        {"t": 13.2, **a, "status": "gap", "gap": "predict", "gap_s": 0.69},
    ]
    for rec in records:
        sink.write(rec)
    used = [r for r in records if r["status"] in ("ok", "masked", "gap")]
    marked = [r for r in records if r["status"] != "ok"]
    samples, stamps = _pull(angles_in, len(used))
    markers, marker_stamps = _pull(status_in, len(marked))
    sink.close()
    sink.write(records[0])  # after close: counted, never raised
    assert sink.n_failed == 1

    assert stamps == [r["t"] or 5e-324 for r in used]
    expect = [[r.get(n, math.nan) for n in ROBOT.angle_names] for r in used]
    np.testing.assert_array_equal(np.array(samples), np.array(expect))
    assert np.array(samples).shape == (len(used), K)
    got = [json.loads(m[0]) for m in markers]
    assert got == [{"t": r["t"], "status": r["status"], "note": r.get("note", "")}
                   for r in marked]
    assert marker_stamps[0] == 12.5 and marker_stamps[2:] == [12.0, 13.2]
    assert marker_stamps[1] > 0  # no time: stamped with local_clock()


def test_lsl_source_errors_and_choice_of_stream(lsl, monkeypatch):
    robot_labels = list(COLUMNS)
    # A label the robot needs is missing: one line naming it and listing the stream's.
    name = unique()
    _partial = sensor_outlet(lsl, name, [n for n in robot_labels if n != "hall2_y_r"], "p")
    with pytest.raises(ValueError, match="no channel labelled 'hall2_y_r'") as exc:
        LslSource(name, ROBOT, resolve_timeout=5.0, settle_s=0.0).open()
    assert "\n" not in str(exc.value) and "hall2_y_l" in str(exc.value)

    name = unique()
    _volts = sensor_outlet(lsl, name, robot_labels, "u", units={"gyro2_y": "furlong/s"})
    with pytest.raises(ValueError, match="channel 'gyro2_y': unit 'furlong/s', expected"):
        LslSource(name, ROBOT, resolve_timeout=5.0, settle_s=0.0).open()

    name = unique()
    _text = sensor_outlet(lsl, name, robot_labels, "s", fmt=lsl.cf_string)
    with pytest.raises(ValueError, match="channel format is string"):
        LslSource(name, ROBOT, resolve_timeout=5.0, settle_s=0.0).open()

    start = time.monotonic()
    with pytest.raises(ValueError, match="no LSL stream named") as exc:
        LslSource(unique("absent"), ROBOT, resolve_timeout=1.0).open()
    assert time.monotonic() - start < 3.0 and "\n" not in str(exc.value)

    # Two robots publishing under one name: --allow-from picks one; without it the first
    # found is used and the other named.
    name = unique()
    outlets = {sid: sensor_outlet(lsl, name, robot_labels, sid) for sid in ("exo-A", "exo-B")}
    chosen = LslSource(name, ROBOT, allow_from="exo-B", resolve_timeout=5.0)
    chosen.open()
    assert "exo-B" in chosen.sender and "exo-A" in chosen.announce
    assert outlets["exo-B"].wait_for_consumers(5.0)
    for k, outlet in enumerate(outlets.values()):
        outlet.push_sample([float(k)] * len(robot_labels), timestamp=50.0 + k)
    pkt = chosen.read(5.0)
    assert pkt.t == 51.0 and pkt.hall_v[0] == 1.0 and chosen.read(0.2) is None
    chosen.close()

    first = LslSource(name, ROBOT, resolve_timeout=5.0)
    first.open()
    other = "exo-A" if "exo-B" in first.sender else "exo-B"
    assert "not used: 1 other stream of that name" in first.announce
    assert f"source_id {other}" in first.announce.split("not used")[1]
    first.close()

    with pytest.raises(ValueError, match="no stream of source_id 'exo-C'.*found .*'exo-[AB]'"):
        LslSource(name, ROBOT, allow_from="exo-C", resolve_timeout=0.5, settle_s=0.0).open()

    # Without pylsl: one line saying what to install.
    monkeypatch.setitem(sys.modules, "pylsl", None)
    with pytest.raises(ValueError, match=r"pip install 'kckf-jax\[lab\]'"):
        LslSource(name, ROBOT)


@pytest.mark.long
def test_command_lsl_in_and_out(lsl, tmp_path):
    """``kckf stream --source lsl://IN --sink lsl://OUT`` in its own process (under the same
    loopback configuration): it resolves the outlet after compiling, takes every sample, and
    its outlet's estimates, read back by an inlet, are the batch filter's (float32)."""
    import subprocess

    from kckf_jax import write_session

    s = simulate(ROBOT, "cyclic", seed=6, duration_s=3.0)
    write_session(s, str(tmp_path / "s"))
    name_in, name_out = unique(), unique()
    outlet = sensor_outlet(lsl, name_in, COLUMNS, unique("exo"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "kckf_jax", "stream", "--source", f"lsl://{name_in}",
         "--sink", f"lsl://{name_out}", "--meta", str(tmp_path / "s" / "meta.json"),
         "--idle-timeout", "3"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    err = ""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        err += line
        if "listening" in line or proc.poll() is not None:
            break
    assert "listening on lsl://" in err, err + proc.stderr.read()
    assert "using LSL stream" in err
    found = lsl.resolve_byprop("name", name_out, 1, 10.0)
    inlet = lsl.StreamInlet(found[0], max_buflen=60)
    inlet.open_stream(5.0)
    assert outlet.wait_for_consumers(5.0)
    t = 100.0 + s.t
    cols = [np.asarray(s.gyro[:, ROBOT.gyro_names.index(n)]) if n in ROBOT.gyro_names
            else np.asarray(s.hall_v[:, ROBOT.hall_names.index(n)]) for n in COLUMNS]
    for i, ti in enumerate(t):
        outlet.push_sample([float(c[i]) for c in cols], timestamp=float(ti))
    got, stamps = _pull(inlet, s.n_steps, timeout=30.0)
    out, rest = proc.communicate(timeout=60)
    assert proc.returncode == 0, rest
    assert f"packets {s.n_steps}, ok {s.n_steps}" in rest
    np.testing.assert_array_equal(stamps, t)
    params = Params.paper_defaults(ROBOT, s.hall_models, dtype=jnp.float32)
    gyro = s.gyro.copy()
    gyro[:, [i for i, n in enumerate(ROBOT.gyro_names) if n not in COLUMNS]] = np.nan
    series = SensorSeries(jnp.asarray(np.diff(t, prepend=t[0]), jnp.float32),
                          jnp.asarray(gyro, jnp.float32), jnp.asarray(s.hall_v, jnp.float32))
    ref = np.asarray(run_filter(params, series, "kckf")[1].angles, np.float64)
    np.testing.assert_allclose(np.array(got), ref, atol=1e-4, rtol=0)
