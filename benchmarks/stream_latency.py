"""Latency and throughput of live filtering, in process and end to end over UDP.

    python benchmarks/stream_latency.py [--json] [--in-process] [--eigen-threads] [--quick]

* In process: ``StreamingFilter.push`` of an already parsed packet (the step: host-to-device
  copy of one reading vector, the jitted step, device-to-host copy of the estimates, the output
  record), and parse + push; median and 99th percentile over 5,000 packets of a recorded-like
  session (1 % of readings missing, so the device step). By parts: the floor of any jitted
  call (a trivial one, same arguments), and ``push`` with the health monitor off
  (``--faults off``), against the default (``isolate``). Also a regular stream (constant
  step, every reading) after the covariance has converged: the host path. The same for the
  exported step (``kckf_jax/export_loader.py``'s ``push_array``).
* End to end: a real ``kckf stream --source udp://... --sink udp://...`` process (and the
  export loader's UDP mode) on loopback; each packet's send time against the arrival of its
  estimate, paced at 100 Hz and 1 kHz, from one sender socket for the whole run (the stream's
  one robot: a new socket per rate would be another sender, ``foreign``), its timestamps
  continuing across rates with a gap between them (the filter predicts across it).
* Sustained rate: bursts of 2 s at increasing rates; the highest rate at which every packet got
  its estimate.
* The floor: a bare Python UDP echo process measured the same way (what the OS, the virtual
  machine's wake-up from idle and Python's socket calls cost without any filtering).
* Per method: ``push`` and the exported step of ``kckf`` beside ``kckf3d`` on a robot with
  joints of three axes (``xyz,xyz,xyz``, exact-rotation walking, 1 % missing), in process.
Simulated bench session (x, y, x, y), float32, async dispatch off (as ``kckf stream`` runs).
``--quick``: a smoke run on tiny sizes (the long tests run it): the figures mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _machine import machine  # noqa: E402

from kckf_jax import (  # noqa: E402
    PacketParser,
    Params,
    StreamingFilter,
    enable_cpu_loops,  # noqa: E402
    low_latency,
    simulate,
    write_session,
)

enable_cpu_loops()  # XLA's CPU loops as one kernel each, before any computation

ROOT = os.path.join(os.path.dirname(__file__), "..")
LOADER = os.path.join(ROOT, "kckf_jax", "export_loader.py")


def packets(s) -> list[bytes]:
    out = []
    for i in range(s.n_steps):
        obj = {"t": float(s.t[i])}
        for names, row in ((s.robot.gyro_names, s.gyro[i]), (s.robot.hall_names, s.hall_v[i])):
            obj.update({n: None if np.isnan(v) else float(v) for n, v in zip(names, row)})
        out.append(json.dumps(obj).encode())
    return out


def stats(us) -> dict:
    us = np.asarray(us)
    return {"median_us": round(float(np.median(us)), 1),
            "p99_us": round(float(np.percentile(us, 99)), 1), "n": int(us.size)}


def _timed(fn, items) -> list[float]:
    out = []
    for item in items:
        t0 = time.perf_counter()
        fn(item)
        out.append((time.perf_counter() - t0) * 1e6)
    return out


def in_process(s, pk, export_path, quick: bool = False) -> dict:
    import jax
    import jax.numpy as jnp

    params = Params.paper_defaults(s.robot, s.hall_models)
    sf = StreamingFilter(params)
    sf.warmup()
    parser = PacketParser(s.robot, params=params)  # as kckf stream's: judges each reading
    parsed = [parser.parse(p) for p in pk]
    step_us = _timed(sf.push, parsed)
    sf.reset()
    full_us = _timed(lambda p: sf.push(parser.parse(p)), pk)
    # By parts: any jitted call's floor (two arguments in, two out, as the step), and the
    # step with the health monitor off.
    x = np.zeros(1 + 3 * s.robot.n_links + s.robot.n_hall, np.float32)
    trivial = jax.jit(lambda a, b: (a + 1.0, b[:8] * 2.0))
    flat = [jax.device_put(jnp.zeros(316, jnp.float32))]

    def call(_):
        flat[0], out = trivial(flat[0], x)
        np.asarray(out)

    call(None)
    floor_us = _timed(call, range(len(parsed)))
    off = StreamingFilter(params.with_faults("off"))
    off.warmup()
    off_us = _timed(off.push, parsed)
    sys.path.insert(0, os.path.dirname(LOADER))
    import export_loader

    ex = export_loader.ExportedStep(export_path)
    x = np.concatenate([s.gyro, s.hall_v], axis=1)
    ex.push_array(0.0, x[0])
    ex.reset()
    ex_us = _timed(lambda i: ex.push_array(float(s.t[i]), x[i]), range(s.n_steps))
    # A regular stream (a device clock's constant step, every reading): after host_after
    # packets the covariance has converged and packets take the host path.
    reg = simulate(s.robot, "cyclic", seed=4, duration_s=30.0 if quick else 80.0,
                   drop_prob=0.0)
    reg.t = np.arange(reg.n_steps) * 0.01
    reg_params = Params.paper_defaults(reg.robot, reg.hall_models)
    sf = StreamingFilter(reg_params, host_path=True)
    sf.warmup()
    parsed = [PacketParser(reg.robot, params=reg_params).parse(p) for p in packets(reg)]
    warm = sf.host_after
    for p in parsed[:warm]:
        sf.push(p)
    host_us, on_host = [], 0
    for p in parsed[warm:]:
        t0 = time.perf_counter()
        sf.push(p)
        host_us.append((time.perf_counter() - t0) * 1e6)
        on_host += sf.on_host
    return {"step": stats(step_us), "parse_and_step": stats(full_us),
            "exported_step": stats(ex_us),
            "step_regular_stream": stats(host_us) | {"fraction_on_host": on_host / len(host_us)},
            "parts": {"jitted_call_floor": stats(floor_us),
                      "step_monitor_off": stats(off_us)}}


def per_method(quick: bool = False) -> dict:
    """Per-packet cost of each Kalman method on a robot with joints of three axes
    (``xyz,xyz,xyz``; exact-rotation walking, recorded-like: 1 % of readings missing): ``push``
    of a parsed packet and the exported step's ``push_array`` (its own export), medians over
    the session's packets, for ``kckf`` beside ``kckf3d`` (issue 49)."""
    sys.path.insert(0, os.path.dirname(LOADER))
    import export_loader

    from kckf_jax.cli import main as kckf

    s = simulate("xyz,xyz,xyz", "walking", seed=5, duration_s=3.0 if quick else 30.0,
                 drop_prob=0.01, kinematics="exact")
    tmp = tempfile.mkdtemp(prefix="kckf-bench-methods-")
    write_session(s, os.path.join(tmp, "s"))
    params = Params.paper_defaults(s.robot, s.hall_models)
    parser = PacketParser(s.robot, params=params)
    parsed = [parser.parse(p) for p in packets(s)]
    x = np.concatenate([s.gyro, s.hall_v], axis=1)
    out = {"layout": "xyz,xyz,xyz", "packets": len(parsed)}
    for method in ("kckf", "kckf3d"):
        sf = StreamingFilter(params, method)
        sf.warmup()
        push_us = _timed(sf.push, parsed)
        path = os.path.join(tmp, f"{method}.jaxexport")
        assert kckf(["export", "--meta", os.path.join(tmp, "s", "meta.json"), "-o", path,
                     "--method", method, "--quiet"]) == 0
        ex = export_loader.ExportedStep(path)
        ex.push_array(0.0, x[0])
        ex.reset()
        ex_us = _timed(lambda i, ex=ex: ex.push_array(float(s.t[i]), x[i]), range(s.n_steps))
        out[method] = {"push": stats(push_us), "exported_step": stats(ex_us)}
    for part in ("push", "exported_step"):
        out[f"{part}_ratio"] = round(out["kckf3d"][part]["median_us"]
                                     / out["kckf"][part]["median_us"], 2)
    return out


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


#: A bare Python UDP echo: the floor that the OS, the VM and Python's socket calls set.
ECHO = """
import socket, sys
rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rx.bind(("127.0.0.1", int(sys.argv[1])))
tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
print("listening", file=sys.stderr, flush=True)
while True:
    tx.sendto(rx.recv(65536), ("127.0.0.1", int(sys.argv[2])))
"""


def _server(kind: str, session_dir: str, export_path: str, port: int, sink_port: int):
    if kind == "echo (floor)":
        cmd = [sys.executable, "-c", ECHO, str(port), str(sink_port)]
    elif kind == "kckf stream":
        cmd = [sys.executable, "-m", "kckf_jax", "stream", "--source",
               f"udp://127.0.0.1:{port}", "--sink", f"udp://127.0.0.1:{sink_port}", "--meta",
               os.path.join(session_dir, "meta.json"), "--quiet"]
    else:
        cmd = [sys.executable, LOADER, export_path, "--udp", f"127.0.0.1:{port}", "--sink",
               f"127.0.0.1:{sink_port}"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    while "listening" not in (line := proc.stderr.readline()):
        if proc.poll() is not None:
            raise RuntimeError(f"{kind} did not start: {line}{proc.stderr.read()}")
    return proc


def run_rate(tx, pk, port, rx, rate_hz, n, t_offset) -> tuple[list, int]:
    """Send ``n`` packets at ``rate_hz`` from ``tx`` (busy-wait pacing); latency per
    estimate (us), and how many estimates came back."""
    sent = {}
    lat = []
    period = 1.0 / rate_hz
    start = time.perf_counter()
    received = 0
    for i in range(n):
        obj = json.loads(pk[i % len(pk)])
        obj["t"] = t_offset + i * period  # strictly increasing across runs
        data = json.dumps(obj).encode()
        due = start + i * period
        while time.perf_counter() < due:
            if due - time.perf_counter() > 0.0003:
                time.sleep(0.0001)  # do not busy-wait a core away from the filter
            try:
                while True:
                    got = json.loads(rx.recv(65536, socket.MSG_DONTWAIT))
                    received += 1
                    if got.get("t") in sent:
                        lat.append((time.perf_counter() - sent.pop(got["t"])) * 1e6)
            except BlockingIOError:
                pass
        sent[obj["t"]] = time.perf_counter()
        tx.sendto(data, ("127.0.0.1", port))
    deadline = time.perf_counter() + 2.0
    while time.perf_counter() < deadline and received < n:
        try:
            got = json.loads(rx.recv(65536, socket.MSG_DONTWAIT))
            received += 1
            if got.get("t") in sent:
                lat.append((time.perf_counter() - sent.pop(got["t"])) * 1e6)
        except BlockingIOError:
            time.sleep(0.0002)
    return lat, received


def end_to_end(kind, pk, session_dir, export_path, quick: bool = False) -> dict:
    port, sink_port = _free_port(), _free_port()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    rx.bind(("127.0.0.1", sink_port))
    # One sender for the whole run: the stream takes one robot's packets.
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    proc = _server(kind, session_dir, export_path, port, sink_port)
    out, t_off = {}, 0.0
    sizes = {100: 50, 1000: 200} if quick else {100: 500, 1000: 2000}
    try:
        run_rate(tx, pk, port, rx, 200, 50 if quick else 200, t_off)  # warm the path
        t_off += 10
        for rate, n in sizes.items():
            lat, got = run_rate(tx, pk, port, rx, rate, n, t_off)
            t_off += 10 + n / rate
            if not lat:
                raise RuntimeError(f"{kind}: no estimate came back at {rate} Hz ({got} "
                                   f"records of {n} packets)")
            out[f"{rate}_hz"] = stats(lat) | {"lost": n - got}
        best = 0
        for rate in (2000,) if quick else (2000, 5000, 10000, 20000, 40000):
            n = (rate // 5) if quick else 2 * rate
            _, got = run_rate(tx, pk, port, rx, rate, n, t_off)
            t_off += 10 + n / rate
            out[f"burst_{rate}_hz_received"] = f"{got}/{n}"
            if got == n:
                best = rate
            else:
                break
        out["sustained_no_loss_hz"] = best
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        rx.close()
        tx.close()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--in-process", action="store_true", help="the in-process figures only")
    ap.add_argument("--eigen-threads", action="store_true",
                    help="leave low_latency()'s XLA flag out (async dispatch still off): what "
                         "the flag is worth")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run on tiny sizes (the long tests run it): the figures mean "
                         "nothing")
    args = ap.parse_args()
    if args.eigen_threads:
        import jax

        jax.config.update("jax_cpu_enable_async_dispatch", False)
    else:
        low_latency()  # before any computation, as kckf stream does
    s = simulate("x,y,x,y", "cyclic", seed=3, duration_s=5.0 if args.quick else 50.0,
                 drop_prob=0.01)
    tmp = tempfile.mkdtemp(prefix="kckf-bench-")
    session_dir = os.path.join(tmp, "s")
    write_session(s, session_dir)
    export_path = os.path.join(tmp, "step.jaxexport")
    from kckf_jax.cli import main as kckf

    assert kckf(["export", "--meta", os.path.join(session_dir, "meta.json"), "-o",
                 export_path, "--quiet"]) == 0
    pk = packets(s)
    doc = {"benchmark": "stream_latency", "machine": machine(), "date": time.strftime("%Y-%m-%d"),
           "xla_flags": os.environ.get("XLA_FLAGS", ""), "quick": args.quick,
           "in_process": in_process(s, pk, export_path, args.quick),
           "methods": per_method(args.quick),
           "udp": {} if args.in_process else {
               k: end_to_end(k, pk, session_dir, export_path, args.quick)
               for k in ("kckf stream", "exported step", "echo (floor)")}}
    floor = doc["udp"].get("echo (floor)")
    for kind, d in doc["udp"].items():
        if floor is not None and kind != "echo (floor)":
            d["1000_hz_median_over_echo"] = round(
                d["1000_hz"]["median_us"] / floor["1000_hz"]["median_us"], 2)
    if args.json:
        print(json.dumps(doc, indent=2))
        return
    ip = doc["in_process"]
    for k, v in {**{n: v for n, v in ip.items() if n != "parts"}, **ip["parts"]}.items():
        extra = (f", on the host path {v['fraction_on_host']:.0%} of packets"
                 if "fraction_on_host" in v else "")
        print(f"in process, {k}: median {v['median_us']} us, p99 {v['p99_us']} us{extra}")
    pm = doc["methods"]
    for m in ("kckf", "kckf3d"):
        print(f"in process, {pm['layout']}, {m}: push median {pm[m]['push']['median_us']} us, "
              f"exported step median {pm[m]['exported_step']['median_us']} us")
    for kind, d in doc["udp"].items():
        for rate in ("100_hz", "1000_hz"):
            print(f"{kind}, UDP loopback at {rate}: median {d[rate]['median_us']} us, p99 "
                  f"{d[rate]['p99_us']} us, lost {d[rate]['lost']}")
        if "1000_hz_median_over_echo" in d:
            print(f"{kind}: 1 kHz median {d['1000_hz_median_over_echo']}x the bare echo's")
        print(f"{kind}: sustained with no loss up to {d['sustained_no_loss_hz']} packets/s "
              f"({', '.join(f'{k}: {v}' for k, v in d.items() if k.startswith('burst'))})")


if __name__ == "__main__":
    main()
