"""The ``kckf`` command (contract: ``../shared/spec/cli.md``).

Everything for machines goes to stdout as JSON; everything for people goes to stderr or files.
Bad input ends with one line naming the file, column or value at fault, and exit status 2
(``--debug`` shows the traceback).

``--quiet`` (before or after the verb) silences progress and messages (``_say``), never the
result a command exists for (``_result``, or JSON on stdout), a warning about the data
(``_warn``: faulty data is always named) or an error. ``--debug`` (likewise) shows the
traceback of an error and the log of ``kckf_jax`` and ``pyxdf`` at DEBUG level on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import os
import sys
import time
import warnings
from collections.abc import Sequence

from ._progress import Progress


class UsageError(ValueError):
    """Bad input from the command line or a file: reported in one line, exit status 2."""


# --------------------------------------------------------------------------- helpers
def _say(args, *lines: str) -> None:
    """Messages for people on stderr (what was written, where, how long): not under
    ``--quiet``."""
    if not getattr(args, "quiet", False):
        _result(*lines)


def _result(*lines: str) -> None:
    """The result a command exists for, for people (a table): on stderr, even under
    ``--quiet`` (stdout is for JSON)."""
    for line in lines:
        print(line, file=sys.stderr)


def _read_sessions(paths: Sequence[str], require_mocap: bool = False, args=None):
    from .._sessions._session import read_session

    plausible = not getattr(args, "accept_implausible", False)
    return [read_session(p, require_mocap=require_mocap, plausible=plausible) for p in paths]


def _gaps(args):
    """The gap policy of ``--gap``, ``--on-gap``, ``--max-predict`` (the same everywhere)."""
    from .._readings._gaps import GapPolicy
    return GapPolicy(gap_s=args.gap, on_gap=args.on_gap, max_predict_s=args.max_predict)


def _warn(args, lines: Sequence[str]) -> None:
    """Findings about the data on stderr (even with ``--json``: stdout stays JSON; even with
    ``--quiet``: faulty data is always named)."""
    for line in lines:
        print(f"kckf {args.verb}: warning: {line}", file=sys.stderr)


def _check_methods(methods: Sequence[str]) -> list[str]:
    from .._models._classes import METHODS

    for m in methods:
        if m not in METHODS:
            raise UsageError(f"--method {m!r}: expected one of {', '.join(METHODS)}")
    return list(dict.fromkeys(methods))


# --------------------------------------------------------------------------- verbs
def cmd_simulate(args) -> int:
    from .._models._robot import Robot
    from .._sessions._session import write_session
    from .._sessions._sim_faults import Fault
    from .._sessions._simulate import SimConfig, parse_effects, simulate

    robot = Robot.from_spec(args.joints)
    faults = [Fault.parse(spec) for spec in args.fault]  # a bad spec: one line, exit 2
    effects = parse_effects(args.effect)  # likewise
    if args.rate is not None:
        effects["sample_rate_hz"] = args.rate  # a bad rate: simulate's one-line ValueError
    if args.range_deg is not None:
        effects["motion_range_deg"] = args.range_deg  # likewise
    session = simulate(robot, args.kind, seed=args.seed, duration_s=args.duration,
                       drop_prob=args.drop_prob, move_s=args.move,
                       device_seed=args.device_seed, faults=faults,
                       kinematics=args.kinematics, config=SimConfig(**effects))
    write_session(session, args.out)
    _say(args, f"wrote {args.out}: {session.n_steps} sensor rows, {len(session.mocap_t)} mocap "
               f"frames, joints {robot.spec}"
               + (f", {args.rate:g} Hz" if args.rate is not None else "")
               + (f", range {args.range_deg:g} deg" if args.range_deg is not None else "")
               + (f", faults: {' '.join(map(str, faults))}" if faults else "")
               + (f", effects: {' '.join(args.effect)}" if args.effect else ""))
    return 0


def cmd_observability(args) -> int:
    from .._analysis._observability import observability_ranks, pose_from_degrees
    from .._models._robot import Robot

    robot = Robot.from_spec(args.joints)
    pose = pose_from_degrees(robot, args.pose, "--pose") if args.pose else None
    print(json.dumps(observability_ranks(robot, pose=pose)))
    return 0


def _one_shot():
    """A command filters each recording once: compile time weighed (``Auto(runs=1)``)."""
    from .._paths import Auto

    return Auto(runs=1)


def cmd_filter(args) -> int:
    from .._paths._run import filter_sessions
    from ._report import bias_step_findings, data_faults, estimate_faults, write_estimates

    method = _check_methods([args.method])[0]
    (session,) = _read_sessions([args.session], args=args)
    params = _load_params(args, [session])
    (est,) = filter_sessions([session], method, params, gaps=_gaps(args),
                             smooth=args.smooth, path=_one_shot(), faults=args.faults)
    _warn(args, data_faults([session], params, _gaps(args), method, [est.faults],
                            args.faults)[1])
    _warn(args, estimate_faults([session], method, [est]))
    _warn(args, bias_step_findings([session], method, [est], params, args.faults)[1])
    write_estimates(args.output, session, est)
    _say(args, f"wrote {args.output}: {session.n_steps} rows of {method} estimates "
               f"({est.path} path)")
    return 0


def cmd_evaluate(args) -> int:
    methods = _check_methods(args.method or ["kckf"])
    sessions = _read_sessions(args.sessions, require_mocap=True, args=args)
    from .._paths._run import common_robot

    robot = common_robot(sessions)
    params = _load_params(args, sessions)
    from ._report import evaluate_sessions, format_table

    doc, angles = evaluate_sessions(sessions, methods, params, args.burn_in, _gaps(args),
                                    smooth=args.smooth, path=_one_shot(), faults=args.faults)
    _warn(args, doc["warnings"])
    if args.plot:
        from ._report import session_name
        from .plots import plot_diagnostics, plot_session

        for i, s in enumerate(sessions):
            plot_session(s, {m: angles[m][i] for m in methods}, args.plot, session_name(s.path),
                         gaps=doc["gaps"].get(s.path, []), faults=doc["faults"][s.path],
                         nis={m: doc["_nis_rows"][m][i] for m in doc["_nis_rows"]})
        for m, r in doc["methods"].items():
            if "diagnostics" in r:
                plot_diagnostics(r["diagnostics"], os.path.join(args.plot, f"diagnostics_{m}.png"),
                                 m)
        _say(args, f"figures in {args.plot}")
    doc.pop("_nis_rows", None)
    if args.json:
        print(json.dumps(doc, indent=None))
    else:
        _result(format_table(doc["methods"], robot, methods,
                             f"RMSE (deg) over {len(sessions)} session(s)"))
        from .._analysis._diagnostics import describe

        for m, r in doc["methods"].items():  # the table's findings (the JSON's "diagnostics")
            if "diagnostics" in r:
                _result(*describe(m, r["diagnostics"]))
    return 0


def _load_params(args, sessions):
    """``--params`` for commands on recorded sessions (None without it: each session then
    uses its own meta.json calibration)."""
    if not getattr(args, "params", None):
        return None
    from .._paths._run import common_robot

    return _params_for(args, common_robot(sessions), None, "the session")


def _params_for(args, robot, hall_models, what: str, missing: str = ""):
    """The parameters a command runs with: ``--params`` (checked against ``robot`` when it is
    known), else the paper defaults for ``robot`` and its Hall calibration."""
    from .._models._params import Params, load_params

    dtype = getattr(args, "dtype", None)
    if getattr(args, "params", None):
        params = load_params(args.params, dtype=dtype)
        if robot is not None and params.robot != robot:
            raise UsageError(
                f"{args.params}: parameters are for joints {params.robot.spec!r} but {what} has "
                f"{robot.spec!r}; fit parameters on sessions of this robot")
        return params
    if robot is None:
        raise UsageError(missing)
    return Params.paper_defaults(robot, hall_models, dtype=dtype)


def _distributed(args) -> None:
    """``--coordinator``: join a ``jax.distributed`` fit (every process runs the same command
    with its own sessions and its own ``--process-id``)."""
    if not args.coordinator:
        return
    if args.num_processes is None or args.process_id is None:
        raise UsageError("--coordinator needs --num-processes N and --process-id I")
    import jax

    # Nothing may start JAX's backend before ``initialize`` (asking which it is would): the
    # CPU collectives are named whatever the backend; only a CPU uses them.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=args.coordinator,
                               num_processes=args.num_processes, process_id=args.process_id)


def cmd_fit(args) -> int:
    from .._fitting._fit import FitConfig, FitInterrupted, fit, fit_info
    from .._models._effects import parse_learn
    from .._models._params import save_params
    from .._paths._run import common_robot
    from ._report import data_faults

    _distributed(args)
    mocap = args.loss != "nll"  # the likelihood needs no motion capture
    sessions = _read_sessions(args.sessions, require_mocap=mocap, args=args)
    val = _read_sessions(args.val or [], require_mocap=mocap, args=args)
    common_robot(sessions + val)
    method = _check_methods([args.method])[0]
    _warn(args, data_faults(sessions + val, None, _gaps(args), method,
                            faults=args.faults)[1])
    config = FitConfig(steps=args.steps, learning_rate=args.lr, hall_noise=args.noise,
                       method=method,
                       freeze=tuple(args.freeze or ()), burn_in_s=args.burn_in,
                       batch_size=args.batch_size, seed=args.seed, loss=args.loss,
                       smooth=args.smooth, learn=parse_learn(args.learn), faults=args.faults,
                       **({} if args.nll_weight is None else {"nll_weight": args.nll_weight}))
    init = None
    if args.init:
        from .._models._params import load_params

        init = load_params(args.init)
    ckpt = args.checkpoint or f"{args.output}.ckpt"
    bar = Progress(config.steps, "fit", args.quiet)
    last = {"val": None}

    def on_step(rec):
        unit = next(k for k in rec if k.startswith("loss_"))[len("loss_"):]
        if rec[f"val_{unit}"] is not None:
            last["val"] = rec[f"val_{unit}"]
        val_txt = f" val {last['val']:.3f}" if last["val"] is not None else ""
        bar.update(1, f"loss {rec[f'loss_{unit}']:.3f} {unit.replace('_plus_', '+')}{val_txt}")

    try:
        result = fit(sessions, val, config, init=init, checkpoint=ckpt, resume=args.resume,
                     callback=on_step, gaps=_gaps(args), dtype=args.dtype)
    except FitInterrupted as exc:
        bar.close()
        print(f"kckf fit: {exc}", file=sys.stderr)
        return 130
    bar.close()
    import jax

    if jax.process_index() == 0:  # one writer under --coordinator
        save_params(result.params, args.output, fit_info(result, sessions, val, config))
        if os.path.exists(ckpt):
            os.remove(ckpt)
    best = {"deg": "best_rmse_deg", "nats": "best_nll_nats"}.get(result.unit,
                                                                 f"best_{result.unit}")
    summary = {"params": args.output, "best_step": result.best_step, "loss": args.loss,
               best: result.best_loss_deg, "selected_on": "val" if val else "train",
               "steps_done": result.steps_done, "stopped_early": result.stopped_early,
               "seconds": round(result.seconds, 2), "smoothed": config.smooth,
               "learned": list(config.learn), "progress": fit_progress(result)}
    if args.plot:
        from .plots import plot_fit_progress

        path = plot_fit_progress(summary["progress"], result.best_step,
                                 os.path.join(args.plot, "fit_progress.png"))
        _say(args, f"the fit's progress in {path}")
    print(json.dumps(summary))
    return 0


def fit_progress(result) -> dict:
    """The fit's loss by step (``FitResult.history``) for the JSON and the figure: for the
    parameters after ``updates`` updates (the count ``best_step`` gives for the ones kept),
    ``train`` (the training loss on that step's batch) and ``val`` (the validation loss where
    it was computed, else ``None``), in ``unit``."""
    unit = result.unit
    return {"unit": unit, "updates": [r["step"] - 1 for r in result.history],
            "train": [r[f"loss_{unit}"] for r in result.history],
            "val": [r.get(f"val_{unit}") for r in result.history]}


def cmd_stream(args) -> int:
    import signal

    import kckf_jax._stream as st

    from .._sessions._session import read_meta, read_session

    st.low_latency()  # before the first computation: it sets XLA's thread flags
    method = _check_methods([args.method])[0]
    session = None
    if st.replay_path(args.source):
        session = read_session(st.replay_path(args.source),
                               plausible=not args.accept_implausible)
    robot, hall_models, limits = (
        read_meta(args.meta) if args.meta else (None, None, None) if session is None
        else (session.robot, session.hall_models, session.limits))
    params = _params_for(args, robot, hall_models, "the stream",
                         "the robot layout is unknown: give --meta meta.json, --params FILE or "
                         "a replay://SESSION source")
    if limits is not None:  # the recording's own statement about its hardware
        params = dataclasses.replace(params, limits=limits)
    params = params.with_faults(args.faults)
    gaps = _gaps(args)
    sf = st.StreamingFilter(params, method, gap_s=gaps.gap_s, on_gap=gaps.on_gap,
                            max_predict_s=gaps.max_predict_s)
    sf.warmup()  # compiled before the source opens (or an LSL stream is resolved)

    def say(line: str, always: bool = False) -> None:
        """A message (not under ``--quiet``); ``always``: the contract's readiness line."""
        if always or not args.quiet:
            print(f"kckf stream: {line}", file=sys.stderr, flush=True)

    source = st.open_source(args.source, session, realtime=args.realtime, robot=params.robot,
                            allow_from=args.allow_from, on_sender=lambda s: say(
                                f"taking packets from {s} (the first sender heard; "
                                "--allow-from chooses)"),
                            handover_s=args.handover_after,
                            on_handover=lambda old, new, silence_s: say(
                                f"sender {old} silent {silence_s:.2f} s; taking {new} "
                                "(same host) as the same robot"))
    sink = st.open_sink(args.sink, flush=session is None or args.realtime, robot=params.robot)
    stop = {"now": False}
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.update(now=True))
    source.open()
    if getattr(source, "announce", ""):
        say(source.announce)
    buf = getattr(source, "rcvbuf_actual", None)
    extra = f", receive buffer {buf} bytes" if buf else ""
    # Printed even under --quiet: scripts wait for it before sending (../shared/spec/cli.md).
    say(f"listening on {source.description} (method {method}, {params.log_q.dtype}{extra})",
        always=True)
    try:
        counts = st.run_stream(source, sink, sf,
                               # each reading judged as the step does: a clean packet in one
                               # check, which the host path then need not repeat
                               st.PacketParser(params.robot, params=params),
                               max_packets=args.max_packets, idle_timeout=args.idle_timeout,
                               should_stop=lambda: stop["now"])
    finally:
        source.close()
    if source.foreign:
        _warn(args, ["packets from other senders not used (status foreign): "
                     + ", ".join(f"{k} x{v}" for k, v in source.foreign.items())])
    faulty = counts.pop("faulty", {})
    if faulty:
        _warn(args, ["faulty readings not used (limits "
                     f"{params.limits.describe()}; docs/faults.md): "
                     + ", ".join(f"{k} x{v}" for k, v in faulty.items())])
    _say(args, "kckf stream: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    return 0


def cmd_export(args) -> int:
    from .._sessions._session import read_meta
    from .._stream._export import export_step

    robot, hall_models, limits = read_meta(args.meta) if args.meta else (None, None, None)
    params = _params_for(args, robot, hall_models, "meta.json",
                         "give --params FILE (fitted) or --meta meta.json (paper defaults)")
    if limits is not None:
        params = dataclasses.replace(params, limits=limits)
    params = params.with_faults(args.faults)
    method = _check_methods([args.method])[0]
    n = export_step(params, args.output, method=method, baked=not args.pass_params,
                    gaps=_gaps(args))
    _say(args, f"wrote {args.output} ({n} bytes): {method} step for joints "
               f"{params.robot.spec}, parameters {'passed' if args.pass_params else 'baked in'}; "
               "run it with kckf_jax/export_loader.py (imports only jax and numpy)")
    return 0


def cmd_experiment(args) -> int:
    t0 = time.perf_counter()
    if args.name == "arm-imu":
        from ..filters import arm_imu_experiment

        result = arm_imu_experiment(seed=args.seed)
    else:
        from ..filters import markov_experiment

        if args.runs < 1:
            raise UsageError(f"--runs {args.runs}: expected at least 1")
        result = markov_experiment(runs=args.runs, seed=args.seed)
    from ._report import jsonable

    result = jsonable(result)
    if args.json:
        print(json.dumps(result))
    else:
        _result(json.dumps(result, indent=2))
    _say(args, f"kckf experiment {args.name}: {time.perf_counter() - t0:.1f} s")
    return 0


#: The demo's fit: fixed steps, no validation split (the test sessions stay unseen).
DEMO_FIT_STEPS = 80
DEMO_FIT_LR = 0.06


def data_dir() -> str:
    """The shipped sample sessions (``_demo.data_dir``), or a one-line error."""
    from .._sessions._containers import sample_data_dir as find

    root = find()
    if root is None:
        raise UsageError("the sample sessions are missing: reinstall kckf-jax (pip install .)")
    return root


def cmd_demo(args) -> int:
    from ._demo import run_demo

    t0 = time.perf_counter()
    bars = {}

    def progress(ds, total, rec):
        if ds not in bars:
            bars[ds] = Progress(total, f"fit {ds}", args.quiet)
        bars[ds].update(1, f"loss {rec['loss_deg']:.3f} deg")
        if rec["step"] == total:
            bars[ds].close()

    for text in run_demo(data_dir(), args.out, args.steps, DEMO_FIT_LR, progress):
        for bar in bars.values():
            bar.close()
        bars.clear()
        _result("", text)  # each data set's table: the demo's result
    _say(args, "", f"wrote {args.out}/table.md, {args.out}/results.json, {args.out}/*_params"
                   f".json and {args.out}/figures/ ({time.perf_counter() - t0:.1f} s)")
    return 0


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from ._parser import build_parser as build

    g = globals()
    return build({name: g[name] for name in g if name.startswith("cmd_")}, DEMO_FIT_STEPS)


#: The loggers ``--debug`` turns on: the package's and the XDF reader's (``_xdf`` keeps
#: pyxdf's quiet unless the package's logger is enabled for DEBUG).
DEBUG_LOGGERS = ("kckf_jax", "pyxdf")


class _StderrHandler(logging.StreamHandler):
    """Log lines to whatever ``sys.stderr`` is when they are written (a test's capture too)."""

    def __init__(self):
        super().__init__(sys.stderr)
        self.setFormatter(logging.Formatter("%(name)s: %(levelname)s: %(message)s"))

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):  # StreamHandler's own assignment: the property decides
        pass


@contextlib.contextmanager
def _debug_logging(on: bool):
    """``--debug``: ``DEBUG_LOGGERS`` at DEBUG level with a handler on stderr, for the
    command's run (as they were afterwards: ``main`` may run again in one process)."""
    if not on:
        yield
        return
    handler = _StderrHandler()
    saved = []
    for name in DEBUG_LOGGERS:
        log = logging.getLogger(name)
        saved.append((log, log.level))
        log.setLevel(logging.DEBUG)
        log.addHandler(handler)
    try:
        yield
    finally:
        for log, level in saved:
            log.removeHandler(handler)
            log.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    with _debug_logging(args.debug):
        return _run(args)


def _run(args) -> int:
    """The chosen verb, its errors in one line (``--debug``: the traceback)."""
    import jax

    from .._paths._cpu_loops import enable_cpu_loops
    from ._cache import keep_compiled_programs

    enable_cpu_loops()  # the command's own process, before any computation (KCKF_XLA_LOOPS)
    if getattr(args, "dtype", None) == "float64":
        jax.config.update("jax_enable_x64", True)
    keep_compiled_programs()
    try:
        with warnings.catch_warnings():  # a library's warning: one line for people, not raw
            warnings.showwarning = lambda msg, cat, *a, **k: _warn(args, [
                str(msg) if cat.__name__ == "SessionWarning" else f"{cat.__name__}: {msg}"])
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("kckf: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:  # SessionError, UsageError, bad params, missing files
        if args.debug:
            raise
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, OSError) and exc.filename:
            msg = f"{exc.filename}: {exc.strerror}"
        print(f"kckf {args.verb}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
