"""Evaluation reports: every method's error figures on recorded sessions, as the
``kckf evaluate --json`` document, and the paper's Table 1 layout as text and Markdown.

At the edge with the CLI and the plots: it calls the core (``filter_sessions``,
``rmse_table``) and nothing of the core imports it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .._analysis._diagnostics import consistency_figures, diagnostics, session_innovations
from .._analysis._metrics import rmse_table
from .._models._classes import MODELS, exact_kinematics, model_of
from .._models._fault_policy import FaultPolicy
from .._models._params import Params
from .._paths import AbstractPath
from .._paths._run import filter_sessions, series_faults, session_params, session_series
from .._readings._bias_steps import bias_steps, describe_bias_steps
from .._readings._drift import describe_drift, hall_drift
from .._readings._gaps import GapPolicy, find_gaps
from .._readings._gaps import describe as describe_gaps
from .._readings._mismatch import describe_mismatch, model_mismatch
from .._readings._screen import OUT_OF_RANGE, describe_faults, fault_stretches
from .._readings._setup_check import describe as describe_setup
from .._readings._setup_check import setup_check
from .._sessions._session import Session

PAPER_TABLE_METHODS = ("gyro", "hall_l", "hall_r", "kf", "kckf")
#: The Table 1 columns' labels: each model's own (``AbstractModel.label``), and the demo's
#: fitted columns.
TABLE_LABELS = {**{n: m.label for n, m in MODELS.items()}, "kckf_fit": "KCKF fit",
                "kckf_fit_smoothed": "smoothed"}


def data_faults(sessions: Sequence[Session], params: Params | None = None,
                gaps: GapPolicy = GapPolicy(), method: str = "kckf",
                codes: Sequence[np.ndarray] | None = None, faults=None
                ) -> tuple[dict, list[str]]:
    """What is wrong with the data, before any filter runs: per session, the readings the
    filter does not use because they cannot be measurements (``_screen``: outside the
    physical range, railed, unreachable, saturated) or that stopped following their joint
    (``_health``: noisy, stuck), by column, kind and stretch of time, and
    the gaps in the sensor rows (and what the filter does across them). Returns the JSON form
    ``{"faults": {session: [{"column", "kind", "from_s", "to_s", "count"}]}, "out_of_range":
    {session: {column: {"count", "first_t_s"}}}, "gaps": {session: [gap, ...]}}`` (every
    session in ``"faults"``, an empty list when clean; the others only sessions with something
    to say), the set-up mistakes the first seconds show (``"setup"``: ``setup_check``; a
    joint whose angle cannot be estimated is a ``ValueError`` naming it) and one line for
    people per finding. ``method``: whose model of the gyros judges them (``kckf3d``: no two
    gyros measure the same rate, ``_screen.stand_ins``). ``codes``: each session's fault
    codes where a filter of ``method`` already screened it (``Estimate.faults``), so the
    readings are not judged twice. ``"model_mismatch"``: per session, the paper's gyro pairs
    that follow the pose instead of reading one rate (``_mismatch``); ``"hall_drift"``: the
    joint axes whose two Hall sensors drift apart slowly (``_drift``). ``faults``: the fault
    policy (``FaultPolicy`` or its name; default ``params``' own, else ``isolate``): under
    ``report`` the monitor's findings are named as still used."""
    found_faults, out_of_range, gap_doc, setup, lines = {}, {}, {}, {}, []
    mismatch, drift = {}, {}
    plist = session_params(sessions, params, faults=faults)
    for i, (s, p) in enumerate(zip(sessions, plist)):
        key = s.path or "session"
        names = s.robot.gyro_names + s.robot.hall_names
        if codes is not None:
            codes_i = np.asarray(codes[i])
        else:
            codes_i = np.asarray(series_faults(p, session_series(s, p.log_q.dtype), method))
        found_faults[key] = fault_stretches(s.t, codes_i, names)
        cols = {}
        for j in np.flatnonzero((codes_i == OUT_OF_RANGE).any(axis=0)):
            rows = np.flatnonzero(codes_i[:, j] == OUT_OF_RANGE)
            cols[names[j]] = {"count": int(rows.size), "first_t_s": float(s.t[rows[0]])}
        if cols:
            out_of_range[key] = cols
        line = describe_faults(key, found_faults[key], p.faults)
        if line:
            lines.append(line)
        pairs = model_mismatch(s, method, p, codes_i)
        if pairs:
            mismatch[key] = pairs
            lines.append(describe_mismatch(key, pairs))
        pairs = hall_drift(s, p, codes_i)
        if pairs:
            drift[key] = pairs
            lines.append(describe_drift(key, pairs))
        found = setup_check(s, p, exact=exact_kinematics(method))
        if found:
            setup[key] = [dataclasses.asdict(f) for f in found]
            lines += [f"{key}: {x}" for x in describe_setup(found)]
            errors = [f for f in found if f.severity == "error"]
            if errors:
                raise ValueError(f"{key}: {errors[0].message}: its angle cannot be estimated "
                                 f"from this data; {errors[0].fix}")
        found = find_gaps(s.t, gaps)
        if found:
            gap_doc[key] = [g.to_json() for g in found]
            lines.append(describe_gaps(key, found))
    return {"faults": found_faults, "setup": setup, "out_of_range": out_of_range,
            "gaps": gap_doc, "model_mismatch": mismatch, "hall_drift": drift,
            "fault_policy": str(plist[0].faults)}, lines


def estimate_faults(sessions: Sequence[Session], method: str, estimates) -> list[str]:
    """Lines for people about the steps a filter skipped (its update was not finite; the state
    was kept)."""
    lines = []
    for s, e in zip(sessions, estimates):
        skipped = np.asarray(e.skipped) if e.skipped is not None else np.zeros(0, bool)
        if skipped.any():
            rows = np.flatnonzero(skipped)
            lines.append(f"{s.path or 'session'}: {method}: {rows.size} update(s) were not "
                         f"finite and were skipped, the state kept (first at t = "
                         f"{s.t[rows[0]]:.6g} s)")
    return lines


def bias_step_findings(sessions: Sequence[Session], method: str, estimates,
                       params: Params | None = None, faults=None) -> tuple[dict, list[str]]:
    """The gyro bias steps a filter without gyro pairs absorbed (``kckf3d``: ``_bias_steps``,
    from its own bias estimates; under ``kckf`` the health monitor names them from the pairs):
    ``({session: [step, ...]}, lines)``, sessions without a step left out. Nothing under the
    fault policy ``off`` (``faults``, else ``params``' own), nor for a method with pairs."""
    policy = FaultPolicy.of(faults if faults is not None else
                            (params.faults if params is not None else None))
    if not exact_kinematics(method) or not policy.monitors:
        return {}, []
    found, lines = {}, []
    for s, e in zip(sessions, estimates):
        steps = bias_steps(s, e)
        if steps:
            key = s.path or "session"
            found[key] = steps
            lines.append(describe_bias_steps(key, method, steps))
    return found, lines


def clock_corrected(sessions: Sequence[Session], params: Params | None) -> list[Session]:
    """``sessions`` with motion capture aligned by the learned clock offset of ``params``
    (``Params.effects``, ``"offset"``: the motion capture lags the sensors by ``tau``, so a
    frame belongs ``tau`` earlier on the sensors' clock); as they are without one."""
    effects = None if params is None else params.effects
    if effects is None or not effects.uses("offset"):
        return list(sessions)
    tau = float(effects.time_offset_s)
    return [dataclasses.replace(s, mocap_time_offset_s=s.mocap_time_offset_s - tau)
            if s.mocap is not None else s for s in sessions]


def evaluate_sessions(sessions: Sequence[Session], methods: Sequence[str],
                      params: Params | None = None, burn_in_s: float = 0.0,
                      gaps: GapPolicy = GapPolicy(), smooth: bool = False,
                      path: str | AbstractPath = "auto", faults=None):
    """Every method on ``sessions``: the ``kckf evaluate --json`` document and the estimated
    angles ``{method: [(T, K) per session]}``.

    Each method has its RMSE table (``rmse_table``: with the count of steps that have truth
    and of steps scored), the ``"path"`` that computed it and the ``"skipped_updates"``, and
    the Kalman filters their consistency (``"nis"``, ``"nees"``: ``consistency_figures``);
    the document has what is wrong with the data (``data_faults``; and ``"bias_steps"``:
    ``bias_step_findings`` of the method that judged the data) and ``"warnings"``: one
    line for people per finding, and per method whose RMSE is over fewer steps than have
    truth. ``smooth``: the Kalman methods' smoothed estimates are scored (``"smoothed":
    true``; their NIS is the filter's). The Kalman filters' ``"diagnostics"``
    (``_diagnostics.diagnostics``): the whiteness of the filter's innovations, the error of
    the estimates scored decomposed. ``"_nis_rows"`` (not for the JSON) has each Kalman
    method's per-row NIS for the plots. ``path``: as ``filter_sessions``' (the command passes
    ``Auto(runs=1)``: it filters each batch once).

    Raises ``ValueError`` naming the session when one has no motion capture over its sensor
    rows."""
    for s in sessions:
        if not s.has_truth:
            raise ValueError(
                f"{s.path}: no motion capture overlaps the sensors (mocap.csv is needed to "
                "evaluate)"
            )
    sessions = clock_corrected(sessions, params)
    # The data's faults and set-up as the methods see them: under exact kinematics when a
    # method models them (``_screen.stand_ins``, ``setup_check``), so that the paper's
    # first-order checks do not refuse data that kckf3d is there for; each method's own
    # estimates are screened by its own model either way (``filter_sessions``).
    # The consistency figures' innovations come from the filter's own pass where its path
    # computes them there (``Estimate.innovations``: every built-in path and smoother layout,
    # the smoother's forward pass being the filter), so each recording is filtered once; a
    # caller's path without them leaves them to a second pass.
    judge = next((m for m in methods if exact_kinematics(m)), "kckf")
    ests = {}
    if judge in methods:  # its own screening is the data's: the readings judged once
        ests[judge] = filter_sessions(sessions, judge, params, gaps=gaps, smooth=smooth,
                                      path=path, faults=faults,
                                      innovations=model_of(judge).kalman)
    found, warnings = data_faults(sessions, params, gaps, judge,
                                  [e.faults for e in ests[judge]] if ests else None, faults)
    if ests:
        steps, lines = bias_step_findings(sessions, judge, ests[judge], params, faults)
        found["bias_steps"] = steps
        warnings += lines
    out, angles, nis_rows = {}, {}, {}
    for m in methods:
        kalman = model_of(m).kalman
        est = ests.get(m) or filter_sessions(sessions, m, params, gaps=gaps,
                                             smooth=smooth and kalman, path=path,
                                             faults=faults, innovations=kalman)
        angles[m] = [e.angles for e in est]
        out[m] = rmse_table(sessions, angles[m], burn_in_s)
        out[m]["path"] = "+".join(dict.fromkeys(e.path for e in est))
        out[m]["skipped_updates"] = int(sum(np.asarray(e.skipped).sum() for e in est))
        if kalman:
            # (the filter's own pass where it gave them: ``filter_passes`` 1; else a second)
            innov = _pass_innovations(est)
            out[m]["filter_passes"] = 1 if innov is not None else 2
            if innov is None:
                innov = session_innovations(sessions, m, params, gaps, faults)
            figures, nis_rows[m] = consistency_figures(sessions, m, est, params, gaps, innov)
            out[m].update(figures)
            out[m]["diagnostics"] = diagnostics(sessions, est, innov, params, m,
                                                gaps=gaps, burn_in_s=burn_in_s).to_json()
            if smooth:
                out[m]["smoothed"] = True
        warnings += estimate_faults(sessions, m, est)
        short = {n: (out[m]["steps_scored"][n], k) for n, k in out[m]["steps_with_truth"].items()
                 if out[m]["steps_scored"][n] < k}
        if short:
            text = ", ".join(f"{n} {a} of {k}" for n, (a, k) in list(short.items())[:4])
            warnings.append(f"{m}: RMSE over fewer steps than have truth (no estimate at the "
                            f"others): {text}")
    doc = {"methods": out, "sessions": [s.path for s in sessions], **found,
           "warnings": warnings, "_nis_rows": nis_rows}
    return doc, angles


def _pass_innovations(estimates) -> list | None:
    """Each session's innovations from its filter's own pass (``Estimate.innovations``, as
    ``session_innovations`` gives them: float64 ``(nu, var, valid)``), or ``None`` where a
    session has none."""
    if any(e.innovations is None for e in estimates):
        return None
    return [tuple(np.asarray(x, np.float64) for x in e.innovations) for e in estimates]


def format_table(results: dict, robot, methods: Sequence[str], title: str = "") -> str:
    """The paper's Table 1 layout: one row per angle, one column per method, RMSE in deg."""
    cols = [m for m in methods if m in results]
    width = 9
    lines = []
    if title:
        lines.append(title)
    lines.append(f"{'angle':<10}" + "".join(f"{TABLE_LABELS.get(m, m):>{width}}" for m in cols))
    for name in robot.angle_names:
        row = f"{name:<10}"
        for m in cols:
            v = results[m]["rmse_deg"].get(name)
            row += f"{'-':>{width}}" if v is None else f"{v:>{width}.2f}"
        lines.append(row)
    lines.append(f"{'mean':<10}" + "".join(
        f"{results[m]['mean_rmse_deg']:>{width}.2f}" for m in cols))
    return "\n".join(lines)


def markdown_table(results: dict, robot, methods: Sequence[str]) -> str:
    """``format_table`` as a Markdown table."""
    cols = [m for m in methods if m in results]
    lines = ["| angle | " + " | ".join(TABLE_LABELS.get(m, m) for m in cols) + " |",
             "| --- |" + " ---: |" * len(cols)]
    for name in robot.angle_names:
        cells = []
        for m in cols:
            v = results[m]["rmse_deg"].get(name)
            cells.append("-" if v is None else f"{v:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("| mean | " + " | ".join(
        f"{results[m]['mean_rmse_deg']:.2f}" for m in cols) + " |")
    return "\n".join(lines)


def write_estimates(path: str, session: Session, est) -> None:
    """``kckf filter``'s CSV: ``t`` and one column per estimated angle (rad), named as in
    ``mocap.csv``; an angle the method does not estimate is left out, a NaN is an empty cell;
    each number the shortest text that reads back as the same value of the estimates' type."""
    import os

    from .._sessions._csvio import _write_columns

    robot = session.robot
    names = [n for k, n in enumerate(robot.angle_names) if np.isfinite(est.angles[:, k]).any()]
    cols = [robot.angle_names.index(n) for n in names]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    _write_columns(path, ["t", *names], session.t, np.asarray(est.angles)[:, cols])


def session_name(path: str) -> str:
    """A file-name stem for a session folder: its last two path parts, joined by ``_``."""
    import os

    parts = os.path.normpath(path).split(os.sep)
    return "_".join(parts[-2:]) if len(parts) >= 2 else parts[-1]


def jsonable(x):
    """Plain JSON types (NumPy and JAX scalars and arrays become floats and lists)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return jsonable(np.asarray(x).tolist())
    if isinstance(x, bool | int | str | float) or x is None:
        return x
    return float(x)
