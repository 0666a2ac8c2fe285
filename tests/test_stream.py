"""Streaming: the batch filter's step, one packet at a time; it never dies on bad input."""

from __future__ import annotations

import json
import os
import pty
import signal
import socket
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kckf_jax import (
    PacketParser,
    Params,
    Robot,
    SensorSeries,
    Steady,
    StreamingFilter,
    run_filter,
    simulate,
    write_session,
)
from kckf_jax._stream import USED

ROBOT = Robot.from_spec("x,y,x,y")


@pytest.fixture(scope="module")
def session():
    return simulate(ROBOT, "cyclic", seed=9, duration_s=8.0, drop_prob=0.02)


def packet_bytes(s, i) -> bytes:
    obj = {"t": float(s.t[i])}
    for names, row in ((s.robot.gyro_names, s.gyro[i]), (s.robot.hall_names, s.hall_v[i])):
        obj.update({n: None if np.isnan(v) else float(v) for n, v in zip(names, row)})
    return json.dumps(obj).encode()


def batch_angles(s, rows, dtype):
    """``run_filter`` over the given rows of ``s`` only (the packets that arrived)."""
    params = Params.paper_defaults(s.robot, s.hall_models, dtype=dtype)
    t = s.t[rows]
    series = SensorSeries(jnp.asarray(np.diff(t, prepend=t[0]), dtype),
                          jnp.asarray(s.gyro[rows], dtype), jnp.asarray(s.hall_v[rows], dtype))
    return np.asarray(run_filter(params, series, "kckf")[1].angles, np.float64)


BAD = [b"not json", b"[1, 2]", b'{"gyro1_x": 0.1}', b'{"t": "soon"}', b"\xff\xfe\x00",
       b'{"t": NaN}', b"{" * 5000]


@pytest.mark.parametrize(("dtype", "tol"), [(jnp.float32, 1e-4), (jnp.float64, 1e-6)])
def test_stream_equals_batch_with_drops_and_garbage(session, dtype, tol):
    rng = np.random.default_rng(0)
    keep = np.flatnonzero(rng.random(session.n_steps) > 0.05)  # 5 % of packets lost
    sf = StreamingFilter(Params.paper_defaults(ROBOT, session.hall_models, dtype=dtype))
    sf.warmup()
    parser = PacketParser(ROBOT)
    out = []
    for j, i in enumerate(keep):
        if j % 37 == 0:
            rec = sf.push(parser.parse(BAD[j % len(BAD)]))
            assert rec["status"] not in USED and "theta1_x" not in rec
        rec = sf.push(parser.parse(packet_bytes(session, i)))
        assert rec["status"] in ("ok", "masked")
        out.append([rec[n] for n in ROBOT.angle_names])
    ref = batch_angles(session, keep, dtype)
    assert np.max(np.abs(np.asarray(out) - ref)) <= tol


def _regular_session(seconds, seed=3):
    s = simulate(ROBOT, "cyclic", seed=seed, duration_s=seconds, drop_prob=0.0)
    s.t = np.arange(s.n_steps) * 0.01  # an exactly constant step (a device clock's counter)
    return s


@pytest.mark.parametrize(("dtype", "tol"), [(jnp.float32, 2e-5), (jnp.float64, 1e-8)])
@pytest.mark.long
def test_host_path_engages_leaves_and_equals_batch(dtype, tol):
    """Regular complete packets: after ``HEAD_ROWS`` of them the converged map runs on the host.
    A missing Hall reading, a missing used gyro reading and a lost packet each hand the state
    back to the device step; it comes back after another run of regular packets. Throughout,
    the estimates are the batch filter's over the packets that arrived."""
    head = Steady().head_rows(dtype)
    n = 2 * head + 1200
    s = _regular_session(n / 100.0)
    s.hall_v[head + 300, 2] = np.nan
    s.gyro[head + 400, 0] = np.nan  # gyro1_x: a used column
    keep = np.delete(np.arange(s.n_steps), head + 500)  # a lost packet: one step of 0.02 s
    params = Params.paper_defaults(ROBOT, s.hall_models, dtype=dtype)
    sf = StreamingFilter(params, host_path=True)
    sf.warmup()
    parser = PacketParser(ROBOT)
    out, host = [], []
    for i in keep:
        rec = sf.push(parser.parse(packet_bytes(s, i)))
        out.append([rec[n] for n in ROBOT.angle_names])
        host.append(sf.on_host)
    host = np.asarray(host)
    pos = {i: j for j, i in enumerate(keep)}
    assert not host[: head - 1].any() and host[head + 100]
    for i in (head + 300, head + 400, head + 501):
        assert not host[pos[i]], i  # this packet went to the device
    assert host[-1]  # and the host path came back
    ref = batch_angles(s, keep, dtype)
    assert np.max(np.abs(np.asarray(out) - ref)) <= tol
    final = sf.state  # assembled from the host path's state
    series = SensorSeries(jnp.asarray(np.diff(s.t[keep], prepend=0.0), dtype),
                          jnp.asarray(s.gyro[keep], dtype), jnp.asarray(s.hall_v[keep], dtype))
    ref_final, _ = run_filter(params, series, "kckf")
    np.testing.assert_allclose(final.z, ref_final.z, atol=tol * 10, rtol=0)
    np.testing.assert_allclose(final.P, ref_final.P, rtol=1e-4, atol=1e-12)


@pytest.mark.long
def test_host_path_only_where_it_applies():
    s = _regular_session(25.0)
    parser = PacketParser(ROBOT)
    packets = [parser.parse(packet_bytes(s, i)) for i in range(s.n_steps)]
    for kwargs, method in (({}, "kckf"), ({"host_path": True}, "kf")):
        sf = StreamingFilter(Params.paper_defaults(ROBOT, s.hall_models), method, **kwargs)
        assert not any(sf.push(p) and sf.on_host for p in packets)
    sf = StreamingFilter(Params.from_physical(ROBOT, hall_models=s.hall_models,
                                              hall_noise="voltage"), host_path=True)
    assert not any(sf.push(p) and sf.on_host for p in packets)


def test_one_trace_whatever_arrives(session):
    """Packets of every kind, gaps and restarts: the step is traced once (a retrace raises)."""
    sf = StreamingFilter(Params.paper_defaults(ROBOT), on_gap="restart", gap_s=0.2)
    parser = PacketParser(ROBOT)
    for i in range(50):
        sf.push(parser.parse(packet_bytes(session, i)))
        sf.push(parser.parse(BAD[i % len(BAD)]))
    rec = sf.push(parser.parse(json.dumps({"t": float(session.t[50]) + 5.0}).encode()))
    assert rec["status"] == "gap" and rec["gap"] == "restart"
    assert sf._fn._cache_size() == 1


def test_statuses(session):
    sf = StreamingFilter(Params.paper_defaults(ROBOT), gap_s=0.3, max_predict_s=3.0)
    p = PacketParser(ROBOT, max_bytes=2000)
    first = sf.push(p.parse(packet_bytes(session, 0)))
    assert first["status"] == "ok" and set(ROBOT.angle_names) <= set(first)
    cases = {
        b"not json": "malformed", b"[]": "malformed", b'{"gyro1_x": 1}': "missing_t",
        b'{"t": null}': "missing_t", b'{"t": "x"}': "bad_t", b'{"t": Infinity}': "bad_t",
        b'{"t": 0.0}': "out_of_order", b" " * 3000: "oversized",
    }
    for data, status in cases.items():
        rec = sf.push(p.parse(data))
        assert rec["status"] == status, (data, rec)
    t1 = float(session.t[1])
    rec = sf.push(p.parse(json.dumps({"t": t1, "gyro1_x": "fast", "hall1_x_l": 1e9,
                                      "hall1_x_r": 1.5, "extra": 1}).encode()))
    assert rec["status"] == "masked" and "gyro1_x" in rec["note"] and "'extra'" in rec["note"]
    rec = sf.push(p.parse(json.dumps({"t": t1}).encode()))  # duplicate t
    assert rec["status"] == "out_of_order"
    rec = sf.push(p.parse(json.dumps({"t": t1 + 2.0, "hall1_x_l": 1.3}).encode()))
    assert rec["status"] == "gap" and rec["gap"] == "predict" and rec["gap_s"] == pytest.approx(2)
    # The filter's state (the sensors' health, also carried, uses NaN for "not seen yet").
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(sf.state))


def test_gap_restart_equals_a_fresh_filter(session):
    params = Params.paper_defaults(ROBOT, session.hall_models)
    a = StreamingFilter(params, on_gap="restart", gap_s=0.5)
    b = StreamingFilter(params)
    p = PacketParser(ROBOT)
    for i in range(30):
        a.push(p.parse(packet_bytes(session, i)))
    later = [json.loads(packet_bytes(session, i)) for i in range(100, 130)]
    for obj in later:
        obj["t"] += 10.0
        ra = a.push(p.parse(json.dumps(obj).encode()))
        rb = b.push(p.parse(json.dumps(obj).encode()))
        assert ra["theta1_x"] == pytest.approx(rb["theta1_x"], abs=1e-9)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_fuzz_random_bytes_never_raise(data):
    pkt = PacketParser(ROBOT).parse(data)
    assert pkt.status in ("ok", "masked", "malformed", "oversized", "missing_t", "bad_t")


_SF = {}


def _fuzz_filter():
    if "sf" not in _SF:
        _SF["sf"] = StreamingFilter(Params.paper_defaults(ROBOT, dtype=jnp.float32))
        _SF["p"] = PacketParser(ROBOT)
    return _SF["sf"], _SF["p"]


values = st.one_of(st.none(), st.booleans(), st.text(max_size=5),
                   st.floats(allow_nan=True, allow_infinity=True),
                   st.integers(min_value=-10**30, max_value=10**30), st.lists(st.integers(),
                                                                                max_size=2))
keys = st.sampled_from(["t", *ROBOT.gyro_names, *ROBOT.hall_names, "junk", ""])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(keys, values, max_size=30))
def test_fuzz_random_json_never_poisons_the_state(obj):
    sf, p = _fuzz_filter()
    try:
        data = json.dumps(obj, allow_nan=True).encode()
    except (ValueError, OverflowError):
        data = repr(obj).encode()
    rec = sf.push(p.parse(data))
    assert rec["status"] in ("ok", "masked", "gap", "malformed", "missing_t", "bad_t",
                             "out_of_order")
    state = jax.tree_util.tree_leaves(sf.state)  # the filter's (the health's NaN: "unseen")
    assert all(np.isfinite(np.asarray(x)).all() for x in state), rec
    if rec["status"] in USED:
        assert all(np.isfinite(rec[n]) for n in ROBOT.angle_names)


# --------------------------------------------------------------------------- processes
def _start(args, **kw):
    proc = subprocess.Popen([sys.executable, "-m", "kckf_jax", "stream", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
    deadline = time.time() + 120
    line = ""
    while time.time() < deadline:
        line = proc.stderr.readline()
        if "listening" in line or proc.poll() is not None:
            break
    assert "listening" in line, line + proc.stderr.read()
    return proc


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(("dtype", "tol"), [("float32", 1e-4), ("float64", 1e-6)])
@pytest.mark.long
def test_udp_loopback_equals_batch(session, tmp_path, dtype, tol):
    path = str(tmp_path / "s")
    write_session(session, path)
    port = _free_port()
    proc = _start(["--source", f"udp://127.0.0.1:{port}", "--meta", f"{path}/meta.json",
                   "--idle-timeout", "2", "--dtype", dtype])
    rng = np.random.default_rng(1)
    keep = np.flatnonzero(rng.random(session.n_steps) > 0.05)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for j, i in enumerate(keep):
            if j % 50 == 0:
                sock.sendto(BAD[j % len(BAD)][:1000], ("127.0.0.1", port))
            sock.sendto(packet_bytes(session, i), ("127.0.0.1", port))
            if j % 100 == 0:
                time.sleep(0.005)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    recs = [json.loads(line) for line in out.splitlines()]
    ok = [r for r in recs if r["status"] in USED]
    assert len(ok) == len(keep) and len(recs) > len(keep)
    got = np.array([[r[n] for n in ROBOT.angle_names] for r in ok])
    ref = batch_angles(session, keep, jnp.float64 if dtype == "float64" else jnp.float32)
    assert np.max(np.abs(got - ref)) <= tol


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_serial_pty_with_line_noise(session, tmp_path):
    path = str(tmp_path / "s")
    write_session(session, path)
    master, slave = pty.openpty()
    proc = _start(["--source", f"serial://{os.ttyname(slave)}?baud=115200", "--meta",
                   f"{path}/meta.json", "--max-packets", "55", "--idle-timeout", "20"])
    lines = []
    for i in range(50):
        lines.append(packet_bytes(session, i) + b"\n")
        if i % 10 == 0:
            lines.append(b"\x00\xff#garbage!!\r\n")
    os.write(master, b"".join(lines))
    out, err = proc.communicate(timeout=120)
    os.close(master)
    os.close(slave)
    assert proc.returncode == 0, err
    recs = [json.loads(line) for line in out.splitlines()]
    assert [r["status"] for r in recs].count("ok") + [r["status"] for r in recs].count(
        "masked") == 50
    assert sum(r["status"] == "malformed" for r in recs) == 5


def test_replay_sigterm_flushes_and_exits_0(session, tmp_path):
    path = str(tmp_path / "s")
    write_session(session, path)
    proc = _start(["--source", f"replay://{path}", "--realtime"])
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    recs = [json.loads(line) for line in out.splitlines()]
    assert 20 < len(recs) < session.n_steps and all(r["status"] == "ok" for r in recs[:10])


def test_replay_to_udp_sink_and_max_packets(session, tmp_path):
    path = str(tmp_path / "s")
    write_session(session, path)
    port = _free_port()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", port))
    rx.settimeout(30)
    proc = subprocess.run([sys.executable, "-m", "kckf_jax", "stream", "--source",
                           f"replay://{path}", "--sink", f"udp://127.0.0.1:{port}",
                           "--max-packets", "25"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    got = [json.loads(rx.recv(65536)) for _ in range(25)]
    rx.close()
    assert got[-1]["t"] == pytest.approx(session.t[24]) and proc.stdout == ""


def test_stream_needs_a_robot(capsys):
    from kckf_jax.cli import main

    assert main(["stream", "--source", "udp://127.0.0.1:9"]) == 2
    assert "robot layout is unknown" in capsys.readouterr().err


LOADER_CHECK = """
import json, runpy, sys
sys.argv = ["export_loader.py", sys.argv[1]]
try:
    runpy.run_path(sys.argv_loader, run_name="__main__")
except SystemExit:
    pass
assert "kckf_jax" not in sys.modules and "equinox" not in sys.modules, "imported kckf-jax"
"""


@pytest.mark.parametrize("pass_params", [False, True])
def test_export_runs_without_kckf_jax(session, tmp_path, pass_params):
    from kckf_jax.cli import main

    path = str(tmp_path / "s")
    write_session(session, path)
    exp = str(tmp_path / "step.jaxexport")
    args = ["export", "--meta", f"{path}/meta.json", "-o", exp, "--quiet"]
    assert main(args + (["--pass-params"] if pass_params else [])) == 0
    loader = os.path.join(os.path.dirname(__file__), "..", "kckf_jax", "export_loader.py")
    script = LOADER_CHECK.replace("sys.argv_loader", repr(os.path.abspath(loader)))
    n = 200
    stdin = b"\n".join(packet_bytes(session, i) for i in range(n)).decode() + "\n"
    r = subprocess.run([sys.executable, "-c", script, exp], input=stdin, capture_output=True,
                       text=True, timeout=120, cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    recs = [json.loads(line) for line in r.stdout.splitlines()]
    got = np.array([[rec[n] for n in ROBOT.angle_names] for rec in recs])
    ref = batch_angles(session, np.arange(n), jnp.float32)
    assert np.max(np.abs(got - ref)) <= 1e-4


@pytest.mark.long
def test_loader_and_stream_share_one_status_vocabulary(session, tmp_path):
    """The same faulty packets through ``kckf stream``'s filter and the exported step's
    loader: the same status for every one (and the same gap action)."""
    from kckf_jax.cli import main

    path = str(tmp_path / "s")
    write_session(session, path)
    exp = str(tmp_path / "step.jaxexport")
    assert main(["export", "--meta", f"{path}/meta.json", "-o", exp, "--quiet"]) == 0
    good = [json.loads(packet_bytes(session, i)) for i in range(6)]
    t = [g["t"] for g in good]
    packets = [json.dumps(good[0]), json.dumps(good[1] | {"gyro1_x": None}),
               json.dumps(good[2] | {"hall1_x_l": float("nan")}),
               json.dumps(good[3] | {"hall2_y_r": "high"}),
               json.dumps(good[4] | {"hall1_x_r": 1e30}),
               json.dumps(good[5] | {"gyro2_y": float("inf")}),
               json.dumps({"t": t[2]}), json.dumps({"t": t[5]}),
               json.dumps({"t": t[5] + 2.0, "hall1_x_l": 1.3}),
               json.dumps({"t": t[5] + 2.01, "junk": 1}),
               "not json", "[1]", json.dumps({"gyro1_x": 0.1}), json.dumps({"t": "soon"}),
               json.dumps({"t": t[5] + 3.0, "x": "y" * 9000})]
    sf = StreamingFilter(Params.paper_defaults(ROBOT, session.hall_models))
    parser = PacketParser(ROBOT)
    streamed = [sf.push(parser.parse(p.encode())) for p in packets]
    loader = os.path.join(os.path.dirname(__file__), "..", "kckf_jax", "export_loader.py")
    r = subprocess.run([sys.executable, loader, exp], input="\n".join(packets) + "\n",
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    loaded = [json.loads(line) for line in r.stdout.splitlines()]
    got = [(a["status"], a.get("gap")) for a in streamed]
    assert got == [(b["status"], b.get("gap")) for b in loaded]
    assert [g for g, _ in got] == ["ok", "ok", "ok", "masked", "masked", "masked",
                                   "out_of_order", "out_of_order", "gap", "ok", "malformed",
                                   "malformed", "missing_t", "bad_t", "oversized"]
    for a, b in zip(streamed, loaded):
        if a["status"] in USED:
            for n in ROBOT.angle_names:
                assert a[n] == pytest.approx(b[n], abs=1e-4)  # float64 against float32


def test_the_one_kernel_step_is_the_plain_step(monkeypatch):
    """The stream's step runs as the one pass of an XLA while loop (``_one_kernel``: one
    kernel on a CPU, not about ninety): over a session with faults, packet by packet, its
    states and outputs are those of the same step called plainly (to float32 rounding; the
    same faults named at the same packets); it is compiled as one
    kernel here (the tests enable XLA's CPU loops, as the command does); and a packet whose
    time step is not a number runs nothing (the state kept, ``ok = 0``)."""
    import kckf_jax as kk
    from kckf_jax._models._classes import init_state
    from kckf_jax._readings._health import init_health
    from kckf_jax._stream import _filter

    s = simulate(ROBOT, "cyclic", seed=2, duration_s=12.0, device_seed=2, drop_prob=0.02)
    bad = kk.inject_faults(s, [kk.Fault.parse(x) for x in (
        "noise:hall2_y_r@3-5=0.5", "bias_step:gyro3_x@6=0.2", "disconnect:hall4_y_l@8-10")])
    params = Params.paper_defaults(ROBOT, bad.hall_models, dtype=jnp.float32)
    fn, flatten, _ = _filter.stream_step_fn(params, "kckf", health=True)
    flat0 = flatten((init_state(params, "kckf"), init_health(ROBOT, params.log_q.dtype)))
    x = np.c_[np.diff(bad.t, prepend=bad.t[0]), bad.gyro, bad.hall_v].astype(np.float32)
    one = jax.jit(fn)
    assert 'xla_cpu_small_call="true"' in one.lower(flat0, x[0]).compile().as_text()
    one(flat0, x[0])  # traced before the plain step replaces the loop below
    monkeypatch.setattr(_filter, "_one_kernel", lambda f, flat, x: f(flat, x))
    plain = jax.jit(_filter.stream_step_fn(params, "kckf", health=True)[0])
    assert 'xla_cpu_small_call="true"' not in plain.lower(flat0, x[0]).compile().as_text()
    a = b = flat0
    outs_a, outs_b = [], []
    for row in x:
        a, out_a = one(a, row)
        b, out_b = plain(b, row)
        outs_a.append(np.asarray(out_a))
        outs_b.append(np.asarray(out_b))
    outs_a, outs_b = np.array(outs_a), np.array(outs_b)
    K = ROBOT.n_angles
    # The same arithmetic, compiled otherwise: float32 rounding apart.
    np.testing.assert_allclose(outs_a[:, :K], outs_b[:, :K], atol=1e-5)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-3, atol=1e-5)
    codes_a, codes_b = outs_a[:, 2 * K + 1:], outs_b[:, 2 * K + 1:]
    assert np.count_nonzero(codes_a) > 100  # the faults were judged on the way
    np.testing.assert_array_equal(codes_a, codes_b)
    nan_row = x[5].copy()
    nan_row[0] = np.nan
    kept, out = one(a, nan_row)
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(a))
    assert np.asarray(out)[2 * ROBOT.n_angles] == 0.0


def test_the_host_paths_quick_check_is_the_screen():
    """A packet whose readings are all inside ``clean_bounds`` is not screened again on the
    host path; one outside is: either way the record is the full check's (random packets
    around the bounds' ends, a parser given the parameters and one without)."""
    from kckf_jax._readings._screen import clean_bounds

    params = Params.paper_defaults(ROBOT, simulate(ROBOT, "cyclic", seed=1,
                                                   duration_s=1.0).hall_models)
    sf = StreamingFilter(params, host_path=True)
    lo, hi = clean_bounds(sf._checker.params)
    rng = np.random.default_rng(5)
    seen = {True: 0, False: 0}
    for parser in (PacketParser(ROBOT), PacketParser(ROBOT, params=params)):
        for k in range(400):
            width = hi - lo
            x = rng.uniform(lo - 0.01 * width, hi + 0.01 * width)
            x[rng.random(x.size) < 0.05] = np.nan
            obj = {"t": 0.01 * k, **{n: None if np.isnan(v) else float(v)
                                     for n, v in zip(ROBOT.gyro_names + ROBOT.hall_names, x)}}
            pkt = parser.parse(json.dumps(obj).encode())
            full = sf._checker.check(pkt)
            clean = sf._clean(pkt)
            seen[clean] += 1
            if clean or parser.params is not None:  # nothing left for the check to change
                assert (pkt.status, pkt.faults) == (full.status, full.faults)
                np.testing.assert_array_equal(np.r_[pkt.gyro, pkt.hall_v],
                                              np.r_[full.gyro, full.hall_v])
    assert min(seen.values()) > 50
