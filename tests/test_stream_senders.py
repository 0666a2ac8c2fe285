"""One robot per stream, and nothing lost without a word: a UDP source takes one sender's
packets (the first heard, or ``--allow-from``), marks every other's ``foreign``, and counts
what the kernel dropped before it could read it (received + dropped = sent)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from kckf_jax import PacketParser, Params, Robot, StreamingFilter, simulate, write_session
from kckf_jax._stream import USED, UdpSource, open_source, run_stream
from kckf_jax._stream._io import parse_allow_from

ROBOT = Robot.from_spec("x,y")
LOCAL = "127.0.0.1"


def packet(s, i) -> bytes:
    obj = {"t": float(s.t[i])}
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
