"""One robot per stream, and nothing lost without a word: a UDP source takes one sender's
packets (the first heard, or ``--allow-from``), marks every other's ``foreign``, takes the
robot back when it restarts (its host on a new port after a silence: a handover), and counts
what the kernel dropped before it could read it (received + dropped = sent)."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import threading
import time

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
    write_session,
)
from kckf_jax._stream import USED, Foreign, Oversized, UdpSource, open_source, run_stream
from kckf_jax._stream._io import parse_allow_from
from kckf_jax._stream._source import Handover

ROBOT = Robot.from_spec("x,y")
LOCAL = "127.0.0.1"


def packet(s, i, shift: float = 0.0) -> bytes:
    obj = {"t": float(s.t[i]) - shift}
    for names, row in ((s.robot.gyro_names, s.gyro[i]), (s.robot.hall_names, s.hall_v[i])):
        obj.update({n: None if np.isnan(v) else float(v) for n, v in zip(names, row)})
    return json.dumps(obj).encode()


class ListSink:
    def __init__(self):
        self.recs = []

    def write(self, rec):
        self.recs.append(rec)

    def close(self):
        pass


@pytest.fixture(scope="module")
def sessions():
    return (simulate(ROBOT, "cyclic", seed=1, duration_s=3.0),
            simulate(ROBOT, "cyclic", seed=2, duration_s=2.0))


@pytest.fixture(scope="module")
def stream_filter(sessions):
    sf = StreamingFilter(Params.paper_defaults(ROBOT, sessions[0].hall_models))
    sf.warmup()
    return sf


def _sender() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((LOCAL, 0))
    return sock


def _run(source, sf, n_max=None):
    sf.reset()
    sink = ListSink()
    counts = run_stream(source, sink, sf, PacketParser(ROBOT), max_packets=n_max,
                        idle_timeout=0.5)
    return counts, sink.recs


def _angles(recs):
    return np.array([[r[n] for n in ROBOT.angle_names] for r in recs if r["status"] in USED])


def _interleaved(sessions, source, senders):
    """Session A from ``senders[0]`` (first heard) interleaved with B from ``senders[1]``."""
    a, b = sessions
    port = source.sock.getsockname()[1]
    for i in range(a.n_steps):
        senders[0].sendto(packet(a, i), (LOCAL, port))
        if i < b.n_steps and i % 2 == 0:
            senders[1].sendto(packet(b, i), (LOCAL, port))
        if i % 50 == 0:
            time.sleep(0.002)


def test_second_sender_is_foreign_and_changes_nothing(sessions, stream_filter):
    a, b = sessions
    heard = []
    source = UdpSource(LOCAL, 0, on_sender=heard.append)
    source.open()
    senders = [_sender(), _sender()]
    try:
        _interleaved(sessions, source, senders)
        counts, recs = _run(source, stream_filter)
    finally:
        source.close()
    n_b = len(range(0, b.n_steps, 2))
    assert heard == [f"{LOCAL}:{senders[0].getsockname()[1]}"]
    assert counts["foreign"] == n_b and counts["packets"] == a.n_steps + n_b
    assert counts.get("dropped") == 0
    assert source.foreign == {f"{LOCAL}:{senders[1].getsockname()[1]}": n_b}
    assert all("t" in r and r["note"].startswith("from ") for r in recs
               if r["status"] == "foreign")
    # The estimates equal those of A's packets alone.
    alone = UdpSource(LOCAL, 0)
    alone.open()
    try:
        for i in range(a.n_steps):
            senders[0].sendto(packet(a, i), (LOCAL, alone.sock.getsockname()[1]))
        _, recs_a = _run(alone, stream_filter)
    finally:
        alone.close()
        for s in senders:
            s.close()
    np.testing.assert_array_equal(_angles(recs), _angles(recs_a))


def test_allow_from_takes_the_named_sender(sessions, stream_filter):
    a, b = sessions
    senders = [_sender(), _sender()]
    allowed = parse_allow_from([f"localhost:{senders[1].getsockname()[1]}"])
    source = UdpSource(LOCAL, 0, allow_from=allowed)
    source.open()
    try:
        _interleaved(sessions, source, senders)
        counts, recs = _run(source, stream_filter)
    finally:
        source.close()
        for s in senders:
            s.close()
    n_b = len(range(0, b.n_steps, 2))
    assert counts["foreign"] == a.n_steps
    assert len(_angles(recs)) == n_b


def test_allow_from_values():
    assert parse_allow_from(["127.0.0.1:9", "localhost"]) == [(LOCAL, 9), (LOCAL, None)]
    assert parse_allow_from(None) is None
    for bad in ("127.0.0.1:0", "127.0.0.1:x", "no-such-host.invalid"):
        with pytest.raises(ValueError, match="--allow-from"):
            parse_allow_from([bad])
    for one_sender in ("serial:///dev/ttyUSB0?baud=9600", "replay://somewhere"):
        with pytest.raises(ValueError, match="has one sender"):
            open_source(one_sender, allow_from=["127.0.0.1"])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SO_RXQ_OVFL is Linux's")
def test_burst_received_plus_dropped_is_sent(sessions, stream_filter):
    a, _ = sessions
    source = UdpSource(LOCAL, 0, rcvbuf=32 << 10)  # a small buffer: the burst overflows it
    source.open()
    sent = 3000
    port = source.sock.getsockname()[1]
    with _sender() as tx:
        for k in range(sent):  # nothing reads while they arrive
            tx.sendto(packet(a, k % a.n_steps), (LOCAL, port))
    try:
        counts, _ = _run(source, stream_filter)
    finally:
        source.close()
    assert counts["dropped"] > 0
    assert counts["packets"] + counts["dropped"] == sent


@pytest.mark.long
def test_command_names_the_sender_and_counts_foreign(sessions, tmp_path):
    a, b = sessions
    path = str(tmp_path / "s")
    write_session(a, path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((LOCAL, 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "kckf_jax", "stream", "--source",
                             f"udp://{LOCAL}:{port}", "--meta", f"{path}/meta.json",
                             "--idle-timeout", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline:
        line = proc.stderr.readline()
        if "listening" in line or proc.poll() is not None:
            break
    senders = [_sender(), _sender()]
    first = f"{LOCAL}:{senders[0].getsockname()[1]}"
    for i in range(40):
        senders[0].sendto(packet(a, i), (LOCAL, port))
        senders[1].sendto(packet(b, i), (LOCAL, port))
    out, err = proc.communicate(timeout=60)
    for s in senders:
        s.close()
    assert proc.returncode == 0, err
    assert f"taking packets from {first} (the first sender heard" in err
    statuses = [json.loads(x)["status"] for x in out.splitlines()]
    assert statuses.count("foreign") == 40 and statuses.count("ok") == 40
    summary = [x for x in err.splitlines() if "packets 80" in x]
    assert summary and "foreign 40" in summary[0] and "dropped 0" in summary[0]
    assert "Warning" not in err and "Traceback" not in err


# ---------------------------------------------------------------------------- handover
TOL = 1e-4  # float32 stream against float32 batch (tests/test_stream.py)
LOADER = os.path.join(os.path.dirname(__file__), "..", "kckf_jax", "export_loader.py")


def _name(sock) -> str:
    host, port = sock.getsockname()
    return f"{host}:{port}"


def batch_angles(s, rows):
    """``run_filter`` over the given rows of ``s`` only (as tests/test_stream.py)."""
    params = Params.paper_defaults(s.robot, s.hall_models)
    t = s.t[rows]
    series = SensorSeries(jnp.asarray(np.diff(t, prepend=t[0]), params.log_q.dtype),
                          jnp.asarray(s.gyro[rows], params.log_q.dtype),
                          jnp.asarray(s.hall_v[rows], params.log_q.dtype))
    return np.asarray(run_filter(params, series, "kckf")[1].angles, np.float64)


def _live(source, sf, send, n_max, idle=2.5):
    """The stream over ``source`` while ``send(port)`` sends from a thread (the silences
    are measured as packets are read: a live stream)."""
    sf.reset()
    sink = ListSink()
    th = threading.Thread(target=send, args=(source.sock.getsockname()[1],))
    th.start()
    try:
        counts = run_stream(source, sink, sf, PacketParser(ROBOT), max_packets=n_max,
                            idle_timeout=idle)
    finally:
        th.join()
    return counts, sink.recs


def _restart_script(s, k, before, after, silence_s, shift=0.0, dest=LOCAL):
    """Rows ``:k`` from ``before``, ``silence_s`` of silence, rows ``k:`` from ``after`` (the
    restarted robot's new socket; its clock less ``shift``), then one from ``before``."""
    def send(port):
        for i in range(k):
            before.sendto(packet(s, i), (dest, port))
            if i % 10 == 9:
                time.sleep(0.001)
        time.sleep(silence_s)
        for i in range(k, s.n_steps):
            after.sendto(packet(s, i, shift), (dest, port))
            if i % 10 == 9:
                time.sleep(0.001)
        before.sendto(packet(s, s.n_steps - 1), (dest, port))  # the old port: foreign now
    return send


@pytest.mark.parametrize("clock", ["continues", "restarts"])
@pytest.mark.long
def test_restarted_sender_is_taken_back(sessions, stream_filter, clock):
    """A robot that restarts after 1 s of silence comes back from its host on a new port:
    taken back (the default 0.5 s), named; with its clock continuing the estimates are the
    batch filter's over all rows, with its clock started again from 0 the filter restarts
    there and the estimates after it are the batch filter's over those rows alone."""
    a, _ = sessions
    k = 120
    told = []
    source = UdpSource(LOCAL, 0, on_handover=lambda *x: told.append(x))
    source.open()
    with _sender() as before, _sender() as after:  # both open: two different ports
        shift = float(a.t[k]) if clock == "restarts" else 0.0
        send = _restart_script(a, k, before, after, 1.0, shift)
        try:
            counts, recs = _live(source, stream_filter, send, a.n_steps + 1)
        finally:
            source.close()
        old, new = _name(before), _name(after)
    assert counts["packets"] == a.n_steps + 1 and counts["handover"] == 1
    assert counts["foreign"] == 1 and recs[-1]["note"] == f"from {old}"
    assert source.handovers == [(old, new)] and source.foreign == {old: 1}
    assert [(p, q) for p, q, _ in told] == [(old, new)] and 0.5 <= told[0][2] < 5.0
    first = recs[k]
    assert first["handover"] == f"{old} -> {new}"
    assert f"sender {old} silent" in first["note"] and f"taking {new} (same host)" in first["note"]
    assert all("handover" not in r for r in recs[:k] + recs[k + 1:])
    got = _angles(recs[:-1])
    if clock == "continues":
        assert first["status"] in ("ok", "masked") and "gap" not in first
        ref = batch_angles(a, np.arange(a.n_steps))
        assert np.max(np.abs(got - ref)) <= TOL
    else:
        assert first["status"] == "gap" and first["gap"] == "restart"
        assert "clock started again" in first["note"]
        assert np.max(np.abs(got[:k] - batch_angles(a, np.arange(k)))) <= TOL
        assert np.max(np.abs(got[k:] - batch_angles(a, np.arange(k, a.n_steps)))) <= TOL


def test_second_sender_while_the_first_is_live_stays_foreign(sessions, stream_filter):
    """Live, interleaved (the first never silent for the default 0.5 s): no handover."""
    a, b = sessions
    source = UdpSource(LOCAL, 0)
    source.open()
    senders = [_sender(), _sender()]

    def send(port):
        for i in range(a.n_steps):
            senders[0].sendto(packet(a, i), (LOCAL, port))
            if i < b.n_steps and i % 2 == 0:
                senders[1].sendto(packet(b, i), (LOCAL, port))
            if i % 10 == 9:
                time.sleep(0.002)

    n_b = len(range(0, b.n_steps, 2))
    second = _name(senders[1])
    try:
        counts, recs = _live(source, stream_filter, send, a.n_steps + n_b)
    finally:
        source.close()
        for s in senders:
            s.close()
    assert "handover" not in counts and source.handovers == []
    assert counts["foreign"] == n_b and source.foreign == {second: n_b}
    assert np.max(np.abs(_angles(recs) - batch_angles(a, np.arange(a.n_steps)))) <= TOL


def test_handover_off_keeps_the_restart_foreign(sessions, stream_filter):
    a, _ = sessions
    k = 100
    source = UdpSource(LOCAL, 0, handover_s=math.inf)
    source.open()
    with _sender() as before, _sender() as after:
        try:
            counts, _ = _live(source, stream_filter, _restart_script(a, k, before, after, 0.6),
                              a.n_steps + 1)
        finally:
            source.close()
        first = before.getsockname()
    assert "handover" not in counts and source.handovers == []
    assert counts["foreign"] == a.n_steps - k and source.sender == first


def _read(source):
    item = source.read(1.0)
    assert item is not None
    return item


def test_handover_rules():
    """Another host is never taken over; ``allow_from`` is as before (a name with a port
    admits only that port, without one every port of the host); an oversized first packet
    of the new port is handed over as ``Oversized``. Silence is simulated by moving the time
    the sender was last heard (127.0.0.2 is another host on Linux's loopback)."""
    with _sender() as one, _sender() as two, _sender() as three:
        source = UdpSource(LOCAL, 0, max_bytes=100)
        source.open()
        port = source.sock.getsockname()[1]
        try:
            one.sendto(b"a", (LOCAL, port))
            assert _read(source) == b"a"
            two.sendto(b"b", (LOCAL, port))  # the sender is live: foreign
            assert _read(source) == Foreign(_name(two))
            if sys.platform.startswith("linux"):
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other_host:
                    other_host.bind(("127.0.0.2", 0))
                    source._heard -= 10.0
                    other_host.sendto(b"c", (LOCAL, port))
                    assert _read(source) == Foreign(_name(other_host))
            source._heard -= 10.0
            three.sendto(b"x" * 200, (LOCAL, port))
            item = _read(source)
            assert isinstance(item, Handover) and item.data == Oversized(200)
            assert (item.previous, item.sender) == (_name(one), _name(three))
            assert item.silence_s >= 10.0
            one.sendto(b"d", (LOCAL, port))  # the previous port: foreign from now on
            assert _read(source) == Foreign(_name(one))
            three.sendto(b"e", (LOCAL, port))
            assert _read(source) == b"e"
        finally:
            source.close()
        # A port heard while the sender was still sending is another sender: it is not taken
        # over when the sender falls silent (a new port is).
        source = UdpSource(LOCAL, 0, handover_s=0.2)
        source.open()
        port = source.sock.getsockname()[1]
        try:
            with _sender() as four, _sender() as five:
                four.sendto(b"a", (LOCAL, port))
                assert _read(source) == b"a"
                five.sendto(b"b", (LOCAL, port))
                assert _read(source) == Foreign(_name(five))
                four.sendto(b"c", (LOCAL, port))
                assert _read(source) == b"c"
                time.sleep(0.3)
                five.sendto(b"d", (LOCAL, port))
                assert _read(source) == Foreign(_name(five))
                one.sendto(b"e", (LOCAL, port))
                item = _read(source)
                assert isinstance(item, Handover) and item.sender == _name(one)
        finally:
            source.close()
        for allowed, expect in (([(LOCAL, one.getsockname()[1])], Foreign(_name(two))),
                                ([(LOCAL, None)], b"f")):
            source = UdpSource(LOCAL, 0, allow_from=allowed)
            source.open()
            port = source.sock.getsockname()[1]
            try:
                one.sendto(b"a", (LOCAL, port))
                assert _read(source) == b"a"
                source._heard -= 10.0
                two.sendto(b"f", (LOCAL, port))
                assert _read(source) == expect and source.handovers == []
            finally:
                source.close()
        with pytest.raises(ValueError, match="--handover-after"):
            open_source("udp://127.0.0.1:9", handover_s=-1.0)
        del three


def _start_and_wait(cmd):
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    head = []
    while time.time() < deadline:
        line = proc.stderr.readline()
        head.append(line)
        if "listening" in line or proc.poll() is not None:
            break
    return proc, "".join(head)


@pytest.mark.long
def test_command_takes_a_restarted_sender_back(sessions, tmp_path):
    a, _ = sessions
    path = str(tmp_path / "s")
    write_session(a, path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((LOCAL, 0))
        port = probe.getsockname()[1]
    proc, head = _start_and_wait([sys.executable, "-m", "kckf_jax", "stream", "--source",
                                  f"udp://{LOCAL}:{port}", "--meta", f"{path}/meta.json",
                                  "--idle-timeout", "4", "--handover-after", "0.3"])
    k, n = 40, 80
    with _sender() as before, _sender() as after:
        for i in range(k):
            before.sendto(packet(a, i), (LOCAL, port))
        time.sleep(1.5)  # well over 0.3 s however late the reader is on a busy machine
        for i in range(k, n):
            after.sendto(packet(a, i, float(a.t[k])), (LOCAL, port))
        out, err = proc.communicate(timeout=60)
        old, new = _name(before), _name(after)
    err = head + err
    assert proc.returncode == 0, err
    assert f"kckf stream: sender {old} silent " in err
    assert f"s; taking {new} (same host) as the same robot" in err
    recs = [json.loads(x) for x in out.splitlines()]
    assert len(recs) == n and recs[k]["status"] == "gap" and recs[k]["gap"] == "restart"
    assert recs[k]["handover"] == f"{old} -> {new}"
    summary = [x for x in err.splitlines() if f"packets {n}" in x]
    assert summary and "handover 1" in summary[0] and "foreign" not in summary[0]
    assert "Traceback" not in err


@pytest.mark.long
def test_export_loader_udp_one_sender_and_handover(sessions, tmp_path):
    """The exported step's UDP loop: the first sender named, a second live one foreign, the
    restarted robot taken back and the step restarted with its clock."""
    from kckf_jax.cli import main

    a, b = sessions
    path = str(tmp_path / "s")
    write_session(a, path)
    exp = str(tmp_path / "step.jaxexport")
    assert main(["export", "--meta", f"{path}/meta.json", "-o", exp, "--quiet"]) == 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((LOCAL, 0))
        port = probe.getsockname()[1]
    proc, head = _start_and_wait([sys.executable, LOADER, exp, "--udp", f"{LOCAL}:{port}",
                                  "--idle-timeout", "4", "--handover-after", "0.3"])
    k, n = 60, 120
    with _sender() as before, _sender() as after, _sender() as second:
        for i in range(k):
            before.sendto(packet(a, i), (LOCAL, port))
            if i % 3 == 0:
                second.sendto(packet(b, i), (LOCAL, port))
        time.sleep(1.5)  # well over 0.3 s however late the reader is on a busy machine
        for i in range(k, n):
            after.sendto(packet(a, i, float(a.t[k])), (LOCAL, port))
        out, err = proc.communicate(timeout=60)
        old, new, other = _name(before), _name(after), _name(second)
    err = head + err
    assert proc.returncode == 0, err
    assert f"export_loader: taking packets from {old} (the first sender heard" in err
    assert (f"export_loader: sender {old} silent " in err
            and f"s; taking {new} (same host) as the same robot" in err)
    n_foreign = len(range(0, k, 3))
    assert f"export_loader: packets {n + n_foreign}, foreign {n_foreign}, handover 1" in err
    recs = [json.loads(x) for x in out.splitlines()]
    foreign = [r for r in recs if r["status"] == "foreign"]
    assert foreign == [{"t": None, "status": "foreign", "note": f"from {other}"}] * n_foreign
    ours = [r for r in recs if r["status"] != "foreign"]
    assert len(ours) == n and ours[k]["status"] == "gap" and ours[k]["gap"] == "restart"
    assert ours[k]["handover"] == f"{old} -> {new}" and "clock started again" in ours[k]["note"]
    got = _angles(ours)
    assert np.max(np.abs(got[:k] - batch_angles(a, np.arange(k)))) <= TOL
    assert np.max(np.abs(got[k:] - batch_angles(a, np.arange(k, n)))) <= TOL
