"""The ``kckf`` command line's options (contract: ``../shared/spec/cli.md``); the commands
themselves are in ``cli/__init__.py``, which hands them in.

Every option that takes a closed set of values names each of them in its help, from the tuple
the code checks it against: an argparse ``choices``, or, for a value the code checks itself
(a comma-separated list, a repeatable option, a one-line error of its own), the tuple recorded
as the option's ``accepted`` (``_accepts``; tests/test_cli_help.py reads both).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Mapping

#: ``--dtype``'s values (stream, export), the default first.
DTYPES = ("float32", "float64")
#: ``kckf experiment NAME``: each name and what it runs.
EXPERIMENTS = {"arm-imu": "arm exoskeleton + IMU fusion (Chen et al.)",
               "markov": "Markovian (MJLS) KF for a lower-limb exoskeleton, Fig. 9"}
#: ``kckf simulate --effect NAME=SIZE``: the unit of each name's size (``SimConfig``'s).
_SIM_EFFECT_UNITS = {"play": "DEG", "curve": "DEG", "sync": "SEC", "delay": "SEC",
                     "mount": "DEG", "soft": "HZ"}
#: ``--quiet`` and ``--debug``'s help (the main parser's and every verb's copy).
QUIET_HELP = ("no progress bars or messages on stderr; the result (JSON on stdout, the tables "
              "of evaluate, demo and experiment), warnings about the data and errors still "
              "appear")
DEBUG_HELP = ("tracebacks on errors, and the log lines of kckf_jax and of the libraries it "
              "reads files with (pyxdf) at DEBUG level on stderr")


def _listing(values: Iterable[str], notes: Mapping[str, str] | None = None,
             default: str | None = None) -> str:
    """``a (note), b, c`` for a help text: every value of ``values`` (the code's own tuple),
    each with its note where ``notes`` has one and ``default`` marked."""
    out = []
    for v in values:
        extra = [x for x in (("default" if v == default else ""), (notes or {}).get(v, "")) if x]
        out.append(f"{v} ({'; '.join(extra)})" if extra else v)
    return ", ".join(out)


def _accepts(action: argparse.Action, values: Iterable[str]) -> argparse.Action:
    """Record on ``action`` the values the code accepts for it (checked by the code, not by
    argparse's ``choices``: its own one-line error), for the help's tests."""
    action.accepted = tuple(values)  # type: ignore[attr-defined]
    return action


def _common_options(p: argparse.ArgumentParser, default) -> None:
    """``--debug`` and ``--quiet``: on the main parser (``default`` False) and, so that they
    work after the verb too, on every verb's (``default`` ``argparse.SUPPRESS``: a verb that
    is not given them leaves the main parser's value as it is)."""
    p.add_argument("--debug", action="store_true", default=default, help=DEBUG_HELP)
    p.add_argument("--quiet", action="store_true", default=default, help=QUIET_HELP)


def _method_option(p: argparse.ArgumentParser, methods: Iterable[str], text: str = "",
                   **kw) -> None:
    """``--method``: checked by the command (``cli._check_methods``; fit: ``FitConfig``)."""
    methods = tuple(methods)
    _accepts(p.add_argument("--method", metavar="M", **kw,
                            help=(text + "; " if text else "") + "one of "
                            + _listing(methods, default="kckf")), methods)


def _dtype_option(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--dtype", choices=DTYPES, default=DTYPES[0],
                   help=f"{what}: " + _listing(DTYPES, default=DTYPES[0]))


def _data_options(p: argparse.ArgumentParser, plausibility: bool = True) -> None:
    """The options every command on recorded or live data shares: the gap policy and the
    plausibility check."""
    from .._models._fault_policy import FAULT_POLICIES
    from .._readings._gaps import ON_GAP, GapPolicy

    d = GapPolicy()
    p.add_argument("--gap", type=float, default=d.gap_s,
                   help=f"seconds between rows that count as a gap (default {d.gap_s:g})")
    p.add_argument("--on-gap", choices=ON_GAP, default=d.on_gap,
                   help="what the filter does at a gap: " + _listing(
                       ON_GAP, {"predict": "step across it", "restart": "start again after it"},
                       default=d.on_gap))
    p.add_argument("--max-predict", type=float, default=None, metavar="SEC",
                   help="a longer gap restarts even with --on-gap predict (default 1 s)")
    p.add_argument("--faults", choices=FAULT_POLICIES, default="isolate",
                   help="what a sensor the health monitor judges faulty does (docs/faults.md): "
                        + _listing(FAULT_POLICIES, {
                            "isolate": "not used until it behaves again",
                            "report": "named, still used",
                            "off": "no monitor; only the session format's screen"},
                            default="isolate"))
    if plausibility:
        p.add_argument("--accept-implausible", action="store_true",
                       help="read a session whose time step disagrees with sample_rate_hz or "
                            "whose mocap angles exceed 2 pi (refused by default: a unit "
                            "mistake)")


def build_parser(commands: Mapping[str, Callable], demo_steps: int) -> argparse.ArgumentParser:
    """The ``kckf`` parser; ``commands`` maps each ``cmd_*`` name to its function (those of
    ``cli/__init__.py``)."""
    from .._fitting._fit import LOSSES
    from .._models._classes import KALMAN_METHODS, METHODS
    from .._models._effects import EFFECTS as LEARNABLE
    from .._models._params import ALL_LEAVES, HALL_NOISE_MODELS
    from .._sessions._sim_faults import FAULT_KINDS
    from .._sessions._simulate import EFFECTS as SIM_EFFECTS
    from .._sessions._simulate import KINDS, KINEMATICS

    common = argparse.ArgumentParser(add_help=False)
    _common_options(common, argparse.SUPPRESS)

    p = argparse.ArgumentParser(
        prog="kckf",
        description="Kinematically Constrained Kalman Filter for wearable serial-link robots.",
        epilog="--quiet and --debug work before or after the verb (kckf --quiet evaluate ... "
               "is kckf evaluate --quiet ...). --quiet silences progress and messages, never "
               "the result a command exists for, a warning about the data or an error. "
               "--debug turns on the log of kckf_jax and pyxdf (the XDF reader) at DEBUG "
               "level on stderr, and errors show their traceback. kckf VERB --help: each "
               "verb's options and every value they take.")
    _common_options(p, False)
    sub = p.add_subparsers(dest="verb", metavar="VERB")

    d = sub.add_parser("demo", parents=[common], help="the main job on the shipped sample data")
    d.add_argument("--out", default="kckf-demo", help="output folder (default ./kckf-demo)")
    d.add_argument("--steps", type=int, default=demo_steps,
                   help=f"fitting steps per data set (default {demo_steps})")
    d.set_defaults(func=commands['cmd_demo'])

    s = sub.add_parser("simulate", parents=[common], help="write a synthetic session")
    s.add_argument("out", help="session folder to write")
    s.add_argument("--kind", choices=KINDS, default="cyclic",
                   help="the motion (docs/simulator.md): " + _listing(KINDS, default="cyclic"))
    s.add_argument("--kinematics", choices=KINEMATICS, default="linear",
                   help="docs/simulator.md: " + _listing(
                       KINEMATICS, {"linear": "the paper's linear model",
                                    "exact": "exact rotations"}, default="linear"))
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--duration", type=float, default=120.0, help="seconds (default 120)")
    s.add_argument("--joints", default="x,y,x,y", help="axes per joint, e.g. x,y,x,y or xyz,xyz")
    s.add_argument("--drop-prob", type=float, default=0.0,
                   help="probability that a reading is missing (default 0)")
    s.add_argument("--move", type=float, default=60.0,
                   help="static kind: seconds of movement before holding still (default 60)")
    s.add_argument("--device-seed", type=int, default=None, metavar="S",
                   help="seeds the robot itself (Hall curves, gyro scale errors; default: "
                        "--seed): sessions with one device seed are trials of one robot")
    _accepts(s.add_argument(
        "--fault", action="append", default=[], metavar="SPEC",
        help="write a sensor fault (repeatable): KIND:COLUMN[@FROM-TO][=SIZE] or gap@FROM-TO; "
             "KIND one of " + _listing(FAULT_KINDS)
             + " (docs/simulator.md, 'Faults on request')"), FAULT_KINDS)
    _accepts(s.add_argument(
        "--effect", action="append", default=[], metavar="NAME=SIZE",
        help="a sensor effect (repeatable), NAME one of " + _listing(
            (f"{n}={_SIM_EFFECT_UNITS.get(n, 'SIZE')}" for n in SIM_EFFECTS), {
                "play=DEG": "the joints' play as the Hall sensors see it",
                "curve=DEG": "each Hall curve's RMS departure from Eq. 1",
                "sync=SEC": "a motion-capture clock error meta.json does not know",
                "delay=SEC": "the gyros' delay against the Hall sensors",
                "mount=DEG": "each gyro board's tilt on its link (x U(0.5, 1))",
                "soft=HZ": "each gyro board's soft mount, its natural frequency"})
        + "; docs/simulator.md, 'Sensor effects'"), tuple(SIM_EFFECTS))
    s.add_argument("--range-deg", type=float, default=None, metavar="DEG",
                   help="scale the motion so that its largest |angle| (joints and torso) is "
                        "DEG, up to 180, e.g. 140 for arm-like joints (default: each kind's own "
                        "small angles); docs/simulator.md, 'Range and rate'")
    s.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="sensor sample rate, Hz (default 100; MEMS units run at 40-1000)")
    s.set_defaults(func=commands['cmd_simulate'])

    f = sub.add_parser("filter", parents=[common], help="run one filter over a session")
    f.add_argument("session")
    _method_option(f, METHODS, "the filter to run", default="kckf")
    f.add_argument("--params", help="fitted parameters (kckf fit)")
    f.add_argument("-o", "--output", required=True, help="estimates CSV to write")
    f.add_argument("--smooth", action="store_true",
                   help="the fixed-interval (RTS) smoothed estimates instead (Kalman methods: "
                        + _listing(KALMAN_METHODS) + ")")
    _data_options(f)
    f.set_defaults(func=commands['cmd_filter'])

    e = sub.add_parser("evaluate", parents=[common], help="error figures against motion capture")
    e.add_argument("sessions", nargs="+", metavar="SESSION")
    _method_option(e, METHODS, "repeatable", action="append")
    e.add_argument("--params", help="fitted parameters (kckf fit)")
    e.add_argument("--json", action="store_true", help="JSON on stdout")
    e.add_argument("--plot", metavar="DIR", help="write Fig. 5/6-style plots to DIR")
    e.add_argument("--burn-in", type=float, default=0.0, help="seconds left out at the start")
    e.add_argument("--smooth", action="store_true",
                   help="score the fixed-interval (RTS) smoothed estimates (Kalman methods: "
                        + _listing(KALMAN_METHODS) + ")")
    _data_options(e)
    e.set_defaults(func=commands['cmd_evaluate'])

    t = sub.add_parser("fit", parents=[common], help="learned tuning: fit parameters by "
                       "gradient descent (--loss: the RMSE against motion capture, the Hall "
                       "readings' likelihood, or both)")
    t.add_argument("sessions", nargs="+", metavar="SESSION")
    t.add_argument("--plot", metavar="DIR",
                   help="write the fit's progress to DIR/fit_progress.png (the loss by step, "
                        "train and validation, the chosen step marked)")
    _dtype_option(t, "the fit's arithmetic (float64: to check a fit to rounding)")
    t.add_argument("-o", "--output", required=True, help="parameter file to write (JSON)")
    t.add_argument("--val", nargs="+", metavar="SESSION",
                   help="validation sessions: early stopping and choice of the best step")
    t.add_argument("--steps", type=int, default=200, help="maximum gradient steps (200)")
    t.add_argument("--seed", type=int, default=0, help="seeds minibatch draws (0)")
    t.add_argument("--lr", type=float, default=0.03, help="Adam learning rate (0.03)")
    _method_option(t, KALMAN_METHODS, "the filter to fit", default="kckf")
    t.add_argument("--noise", choices=HALL_NOISE_MODELS, default="voltage",
                   help="Hall noise model of the fitted filter: "
                        + _listing(HALL_NOISE_MODELS, default="voltage"))
    _accepts(t.add_argument(
        "--freeze", action="append", metavar="LEAF",
        help="keep a parameter leaf fixed (repeatable), LEAF one of " + _listing(ALL_LEAVES)
             + " (effects.*: only with that effect in --learn)"), ALL_LEAVES)
    t.add_argument("--burn-in", type=float, default=0.0, help="seconds left out of the loss")
    t.add_argument("--loss", choices=LOSSES, default="rmse",
                   help="what is minimised: " + _listing(LOSSES, {
                       "rmse": "against motion capture",
                       "nll": "the likelihood of the Hall readings; needs no mocap.csv",
                       "rmse+nll": "both"}, default="rmse"))
    t.add_argument("--nll-weight", type=float,
                   help="rmse+nll: deg of RMSE per nat of likelihood (FitConfig.nll_weight)")
    t.add_argument("--smooth", action="store_true",
                   help="fit the fixed-interval (RTS) smoothed estimates, the offline output "
                        "(Kalman methods: " + _listing(KALMAN_METHODS)
                        + "; the validation loss smoothed too)")
    _accepts(t.add_argument(
        "--learn", metavar="EFFECTS",
        help="sensor effects to learn too, comma-separated, some of " + _listing(LEARNABLE, {
            "offset": "a clock offset against motion capture",
            "gyro_timing": "where in each step the gyros' rate is taken, their delay",
            "gyro_scale": "each gyro channel's scale error",
            "play": "the joints' mechanical play",
            "curve": "Hall curves beyond Eq. 1",
            "gyro_mounting": "each gyro board's rotation on its link, learned with "
                             "gyro_scale"}) + "; docs/fitting.md"),
        LEARNABLE)
    t.add_argument("--batch-size", type=int, help="trials per step (default all)")
    t.add_argument("--init", help="start from this parameter file instead of the paper's")
    t.add_argument("--checkpoint", help="checkpoint file (default OUTPUT.ckpt)")
    t.add_argument("--resume", action="store_true",
                   help="continue an interrupted fit from its checkpoint")
    t.add_argument("--coordinator", metavar="HOST:PORT",
                   help="fit over several processes (jax.distributed): each runs this command "
                        "with its own sessions; process 0 writes the outputs")
    t.add_argument("--num-processes", type=int, help="with --coordinator: how many processes")
    t.add_argument("--process-id", type=int, help="with --coordinator: this one's (0 .. N-1)")
    _data_options(t)
    t.set_defaults(func=commands['cmd_fit'])

    r = sub.add_parser("stream", parents=[common], help="live filtering of sensor packets")
    r.add_argument("--source", required=True, help="udp://HOST:PORT, serial:///dev/ttyX?baud=B, "
                   "replay://SESSION or lsl://NAME (Lab Streaming Layer)")
    r.add_argument("--sink", default="stdout",
                   help="stdout (default), udp://HOST:PORT or lsl://NAME (+ NAME-status)")
    r.add_argument("--allow-from", action="append", metavar="HOST[:PORT]",
                   help="the sender to take packets from (repeatable; lsl://: its source id); "
                        "default: the first heard; others get the status foreign")
    r.add_argument("--handover-after", type=float, default=0.5, metavar="SEC",
                   help="udp://: once the sender has been silent this long, a packet from its "
                        "host on a new port (a restarted robot) makes that port the sender, "
                        "named on stderr and in the record (default 0.5 s; inf: never); a "
                        "second sender while the first is live stays foreign")
    r.add_argument("--params", help="fitted parameters (kckf fit)")
    r.add_argument("--meta", help="meta.json giving the robot layout and Hall calibration")
    _method_option(r, METHODS, "the filter to run", default="kckf")
    r.add_argument("--max-packets", type=int, help="stop after this many packets")
    r.add_argument("--idle-timeout", type=float, help="stop after this many seconds of silence")
    r.add_argument("--realtime", action="store_true", help="replay at the recorded pace")
    _data_options(r)
    _dtype_option(r, "the filter's arithmetic")
    r.set_defaults(func=commands['cmd_stream'])

    x = sub.add_parser("export", parents=[common],
                       help="serialise the jitted step with jax.export for deployment")
    x.add_argument("--params", help="fitted parameters (kckf fit)")
    x.add_argument("--meta", help="or: meta.json for the paper-default filter of that robot")
    _method_option(x, METHODS, "the filter to export", default="kckf")
    x.add_argument("-o", "--output", required=True, help="file to write (.jaxexport)")
    x.add_argument("--pass-params", action="store_true",
                   help="take the parameters as an input instead of baking them in")
    _dtype_option(x, "the exported step's arithmetic")
    _data_options(x, plausibility=False)
    x.set_defaults(func=commands['cmd_export'])

    xp = sub.add_parser("experiment", parents=[common],
                        help="the other papers' systems: arm exoskeleton + IMU, Markovian KF")
    xsub = xp.add_subparsers(dest="name", metavar="NAME", required=True)
    for name, text in EXPERIMENTS.items():
        e2 = xsub.add_parser(name, parents=[common], help=text)
        e2.add_argument("--seed", type=int, default=0)
        e2.add_argument("--json", action="store_true", help="JSON on stdout")
        if name == "markov":
            e2.add_argument("--runs", type=int, default=20, help="Monte Carlo runs per level")
        e2.set_defaults(func=commands['cmd_experiment'])

    o = sub.add_parser("observability", parents=[common],
                       help="observability ranks of the standard KF and the KCKF")
    o.add_argument("--joints", required=True, help="axes per joint, e.g. x,y,x,y")
    o.add_argument("--pose", metavar="DEG,...",
                   help="joint angles (deg) where kckf3d's local rank is taken (default 0)")
    o.set_defaults(func=commands['cmd_observability'])
    return p
