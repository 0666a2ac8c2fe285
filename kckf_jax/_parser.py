"""The ``kckf`` command line's options (contract: ``../shared/spec/cli.md``); the commands
themselves are in ``cli.py``, which hands them in."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping


def _data_options(p: argparse.ArgumentParser, plausibility: bool = True) -> None:
    """The options every command on recorded or live data shares: the gap policy and the
    plausibility check."""
    from ._fault_policy import FAULT_POLICIES
    from ._gaps import GapPolicy

    d = GapPolicy()
    p.add_argument("--gap", type=float, default=d.gap_s,
                   help=f"seconds between rows that count as a gap (default {d.gap_s:g})")
    p.add_argument("--on-gap", choices=("predict", "restart"), default=d.on_gap,
                   help="predict across a gap (default) or restart the filter after it")
    p.add_argument("--max-predict", type=float, default=None, metavar="SEC",
                   help="a longer gap restarts even with --on-gap predict (default 1 s)")
    p.add_argument("--faults", choices=FAULT_POLICIES, default="isolate",
                   help="what a sensor the health monitor judges faulty does: isolate "
                        "(default: not used until it behaves again), report (named, still "
                        "used) or off (no monitor; docs/faults.md)")
    if plausibility:
        p.add_argument("--accept-implausible", action="store_true",
                       help="read a session whose time step disagrees with sample_rate_hz or "
                            "whose mocap angles exceed 2 pi (refused by default: a unit "
                            "mistake)")


def build_parser(commands: Mapping[str, Callable], demo_steps: int) -> argparse.ArgumentParser:
    """The ``kckf`` parser; ``commands`` maps each ``cmd_*`` name to its function (cli.py's)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    common.add_argument("--quiet", action="store_true", help="no progress or messages")

    p = argparse.ArgumentParser(
        prog="kckf", parents=[common],
        description="Kinematically Constrained Kalman Filter for wearable serial-link robots.")
    sub = p.add_subparsers(dest="verb", metavar="VERB")

    d = sub.add_parser("demo", parents=[common], help="the main job on the shipped sample data")
    d.add_argument("--out", default="kckf-demo", help="output folder (default ./kckf-demo)")
    d.add_argument("--steps", type=int, default=demo_steps,
                   help=f"fitting steps per data set (default {demo_steps})")
    d.set_defaults(func=commands['cmd_demo'])

    s = sub.add_parser("simulate", parents=[common], help="write a synthetic session")
    s.add_argument("out", help="session folder to write")
    s.add_argument("--kind", choices=("cyclic", "static", "human", "walking"), default="cyclic")
    s.add_argument("--kinematics", choices=("linear", "exact"), default="linear", help="the "
                   "paper's linear model (default) or exact rotations (docs/simulator.md)")
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
    s.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="write a sensor fault (repeatable): KIND:COLUMN[@FROM-TO][=SIZE] "
                        "or gap@FROM-TO (docs/simulator.md, 'Faults on request')")
    s.add_argument("--effect", action="append", default=[], metavar="NAME=SIZE",
                   help="a sensor effect (repeatable): play=DEG (the joints' play as the Hall "
                        "sensors see it), curve=DEG (each Hall curve's RMS departure from "
                        "Eq. 1), sync=SEC (a motion-capture clock error meta.json does not "
                        "know), delay=SEC (the gyros' delay against the Hall sensors); "
                        "docs/simulator.md, 'Sensor effects'")
    s.add_argument("--range-deg", type=float, default=None, metavar="DEG",
                   help="scale the motion so that its largest |angle| (joints and torso) is "
                        "DEG, up to 180, e.g. 140 for arm-like joints (default: each kind's own "
                        "small angles); docs/simulator.md, 'Range and rate'")
    s.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="sensor sample rate, Hz (default 100; MEMS units run at 40-1000)")
    s.set_defaults(func=commands['cmd_simulate'])

    f = sub.add_parser("filter", parents=[common], help="run one filter over a session")
    f.add_argument("session")
    f.add_argument("--method", default="kckf")
    f.add_argument("--params", help="fitted parameters (kckf fit)")
    f.add_argument("-o", "--output", required=True, help="estimates CSV to write")
    f.add_argument("--smooth", action="store_true",
                   help="the fixed-interval (RTS) smoothed estimates instead (Kalman methods)")
    _data_options(f)
    f.set_defaults(func=commands['cmd_filter'])

    e = sub.add_parser("evaluate", parents=[common], help="error figures against motion capture")
    e.add_argument("sessions", nargs="+", metavar="SESSION")
    e.add_argument("--method", action="append", help="repeatable (default kckf)")
    e.add_argument("--params", help="fitted parameters (kckf fit)")
    e.add_argument("--json", action="store_true", help="JSON on stdout")
    e.add_argument("--plot", metavar="DIR", help="write Fig. 5/6-style plots to DIR")
    e.add_argument("--burn-in", type=float, default=0.0, help="seconds left out at the start")
    e.add_argument("--smooth", action="store_true",
                   help="score the fixed-interval (RTS) smoothed estimates (kckf, kf, kckf3d)")
    _data_options(e)
    e.set_defaults(func=commands['cmd_evaluate'])

    t = sub.add_parser("fit", parents=[common], help="learned tuning: fit parameters by "
                       "gradient descent (--loss: the RMSE against motion capture, the Hall "
                       "readings' likelihood, or both)")
    t.add_argument("sessions", nargs="+", metavar="SESSION")
    t.add_argument("-o", "--output", required=True, help="parameter file to write (JSON)")
    t.add_argument("--val", nargs="+", metavar="SESSION",
                   help="validation sessions: early stopping and choice of the best step")
    t.add_argument("--steps", type=int, default=200, help="maximum gradient steps (200)")
    t.add_argument("--seed", type=int, default=0, help="seeds minibatch draws (0)")
    t.add_argument("--lr", type=float, default=0.03, help="Adam learning rate (0.03)")
    t.add_argument("--method", default="kckf", help="the filter to fit: kckf, kf or kckf3d")
    t.add_argument("--noise", choices=("voltage", "angle"), default="voltage",
                   help="Hall noise model of the fitted filter (default voltage)")
    t.add_argument("--freeze", action="append", metavar="LEAF",
                   help="keep a parameter leaf fixed, e.g. log_p0_angle (repeatable)")
    t.add_argument("--burn-in", type=float, default=0.0, help="seconds left out of the loss")
    t.add_argument("--loss", choices=("rmse", "nll", "rmse+nll"), default="rmse",
                   help="rmse against motion capture (default), nll: the likelihood of the Hall "
                        "readings (needs no mocap.csv), or both")
    t.add_argument("--nll-weight", type=float,
                   help="rmse+nll: deg of RMSE per nat of likelihood (FitConfig.nll_weight)")
    t.add_argument("--smooth", action="store_true",
                   help="fit the fixed-interval (RTS) smoothed estimates, the offline output "
                        "(Kalman methods; the validation loss smoothed too)")
    t.add_argument("--learn", metavar="EFFECTS",
                   help="sensor effects to learn too, comma-separated: offset (a clock offset "
                        "against motion capture), gyro_scale, play (the joints' mechanical "
                        "play), curve (Hall curves beyond Eq. 1); docs/fitting.md")
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
    r.add_argument("--method", default="kckf")
    r.add_argument("--max-packets", type=int, help="stop after this many packets")
    r.add_argument("--idle-timeout", type=float, help="stop after this many seconds of silence")
    r.add_argument("--realtime", action="store_true", help="replay at the recorded pace")
    _data_options(r)
    r.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    r.set_defaults(func=commands['cmd_stream'])

    x = sub.add_parser("export", parents=[common],
                       help="serialise the jitted step with jax.export for deployment")
    x.add_argument("--params", help="fitted parameters (kckf fit)")
    x.add_argument("--meta", help="or: meta.json for the paper-default filter of that robot")
    x.add_argument("--method", default="kckf")
    x.add_argument("-o", "--output", required=True, help="file to write (.jaxexport)")
    x.add_argument("--pass-params", action="store_true",
                   help="take the parameters as an input instead of baking them in")
    x.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    _data_options(x, plausibility=False)
    x.set_defaults(func=commands['cmd_export'])

    xp = sub.add_parser("experiment", parents=[common],
                        help="the other papers' systems: arm exoskeleton + IMU, Markovian KF")
    xsub = xp.add_subparsers(dest="name", metavar="NAME", required=True)
    for name, text in (("arm-imu", "arm exoskeleton + IMU fusion (Chen et al.)"),
                       ("markov", "Markovian (MJLS) KF for a lower-limb exoskeleton, Fig. 9")):
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
