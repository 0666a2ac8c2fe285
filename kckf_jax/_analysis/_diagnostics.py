"""Diagnostics a user reads: where a filter's error comes from (docs/diagnostics.md).

A consistent filter whose smoother does not beat it is not limited by noise: its model leaves
something out. Two analyses say what, at the edge of the filter (NumPy float64; nothing of the
filter imports this module):

* **whiteness** of the normalised innovations ``nu / sqrt(s)`` of every joint's fused Hall
  reading (``session_innovations``): a consistent filter's are white, zero-mean and of unit
  variance. Per channel, the sample autocorrelation at lags ``1..k`` pooled over sessions
  (each session's, and each stretch the filter restarted, its own: no pair crosses a
  boundary; a pair needs both readings), its 95 % band and the Ljung-Box statistic against
  its chi-square threshold.
* **the error decomposition** against motion capture: per angle, the error ``estimate -
  truth`` regressed jointly (least squares, pooled over sessions) on groups of regressors
  (``GROUPS``): a ``bias`` (the intercept), the ``direction`` of motion (play, hysteresis),
  the ``angle`` (the shape of a sensor curve) and ``time`` (drift, and a clock offset through
  the rate). Each group's part, its share of the mean square, and whether it is significant:
  an F-test of dropping it on an effective sample size, and a practical size.

The error at 100 Hz rows is correlated over seconds, so its rows are not independent: the
F-test counts ``N_eff = N / tau_g`` rows, ``tau_g`` the factor by which that correlation
inflates what the group's regressors take from noise alone (Bartlett's, ``Var(x' w) /
(|x|^2 var(w))`` for the group's part ``x`` with the other groups taken out, ``w`` the
noise): from an autoregressive model of the residual (``_stats.noise_model``; its spectrum
weighted by the part's periodogram, ``_stats.variance_inflation``). For an AR(1) residual and
a slow part that is the textbook ``N (1 - rho1) / (1 + rho1)``; a part that changes sign at
every reversal of the motion (the direction) meets the noise where it is weak, and counts
more rows.

The statistics themselves (quantiles, autocorrelation, the noise model) are ``_stats``'.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import equinox as eqx
import numpy as np

from .._models._classes import AbstractModel, method_name, model_of
from .._models._params import Params
from .._models._robot import Robot
from .._paths._likelihood import consistency
from .._paths._likelihood import innovations as _step_innovations
from .._paths._run import session_params, session_series
from .._readings._gaps import GapPolicy, find_gaps, segments
from .._readings._stats import (
    chi2_quantile95,
    f_quantile,
    least_squares,
    ljung_box,
    noise_model,
    pooled_acf,
    variance_inflation,
)
from .._sessions._session import Session, split_at_gaps

#: The regressor groups of the error decomposition, in the order they are reported.
GROUPS = ("bias", "direction", "angle", "time")
#: ``|rate|`` below this counts as no direction (rad/s; 2 deg/s).
DEAD_ZONE_RAD_S = math.radians(2.0)
#: The rate is the central difference of the estimated angle over +- this (s).
RATE_HALF_WINDOW_S = 0.05
#: A group's part must reach this RMS (deg) to be called significant.
PRACTICAL_DEG = 0.05
#: Fewer usable rows than this: the angle, or the channel, is not reported.
MIN_ROWS = 100
_Z975 = 1.959963984540054  # two-sided


class Whiteness(eqx.Module):
    """One innovation channel's whiteness (``diagnostics``): the normalised innovations of
    joint ``channel``'s fused Hall reading.

    ``count``: readings used; ``mean`` and ``nis`` (mean square; a consistent filter's: 0 and
    1); ``acf`` (lags ``1..k``) and each lag's 95 % band ``band`` (``1.96 / sqrt(pairs)``);
    ``q`` the Ljung-Box statistic over those lags and ``q95`` its 95 % threshold (chi-square,
    ``k`` degrees of freedom); ``white``: ``q <= q95``; ``outside``: the lags whose
    autocorrelation leaves its band."""

    channel: str
    count: int
    mean: float
    nis: float
    acf: np.ndarray
    band: np.ndarray
    q: float
    q95: float
    white: bool
    outside: tuple[int, ...]


def channel_names(robot: Robot, method: str, nb: int, m: int) -> list[str | None]:
    """The joint angle each innovation slot ``(block, row)`` belongs to, flattened (``None``
    for a padding slot): the block layout's ``joint_index`` for ``kckf`` and ``kf``, the
    joint coordinates in order for ``kckf3d`` (one block); ``"block b, row i"`` where no
    layout matches the shape."""
    names = robot.joint_angle_names
    model = model_of(method)
    if model.kalman:
        ji = np.asarray(model.innovation_channels(robot))
        if ji.shape == (nb, m):
            return [names[j] if j >= 0 else None for j in ji.reshape(-1)]
    return [f"block {b}, row {i}" for b in range(nb) for i in range(m)]


def whiteness(innovations: Sequence, pieces: Sequence[Sequence[tuple[int, int]]],
              names: Sequence[str | None], lags: int = 20,
              keep: Sequence[np.ndarray] | None = None) -> tuple[Whiteness, ...]:
    """Every channel's ``Whiteness`` from each session's ``(nu, var, valid)`` (``T Nb m``)
    cut into ``pieces`` (row ranges the filter ran from a fresh state); ``keep``: each
    session's rows to use (``(T,)`` bool; all by default). Channels with fewer than
    ``MIN_ROWS`` readings are left out."""
    out = []
    for c, name in enumerate(names):
        if name is None:
            continue
        series = []
        for i, (nu, var, valid) in enumerate(innovations):
            nu, var = nu.reshape(nu.shape[0], -1)[:, c], var.reshape(var.shape[0], -1)[:, c]
            ok = (valid.reshape(valid.shape[0], -1)[:, c] > 0) & (var > 0) & np.isfinite(nu)
            if keep is not None:
                ok &= keep[i]
            z = np.where(ok, nu / np.sqrt(np.where(ok, var, 1.0)), 0.0)
            series += [(z[a:b], ok[a:b]) for a, b in pieces[i]]
        n = sum(int(ok.sum()) for _, ok in series)
        if n < max(MIN_ROWS, 2 * lags):
            continue
        acf, pairs, _ = pooled_acf(series, lags)
        band = _Z975 / np.sqrt(np.maximum(pairs, 1))
        q, q95 = ljung_box(acf, pairs, n), chi2_quantile95(lags)
        allz = np.concatenate([z[ok] for z, ok in series])
        out.append(Whiteness(
            channel=name, count=n, mean=float(allz.mean()), nis=float(np.mean(allz**2)),
            acf=acf, band=band, q=q, q95=q95, white=bool(q <= q95),
            outside=tuple(int(k + 1) for k in np.flatnonzero(np.abs(acf) > band))))
    return tuple(out)


# -------------------------------------------------------------------- error decomposition
def angle_rate(t: np.ndarray, angle: np.ndarray, half_window_s: float = RATE_HALF_WINDOW_S,
               sample_rate_hz: float = 100.0) -> np.ndarray:
    """The time derivative of ``angle`` (``(T, ...)`` rad) at times ``t`` (s): the central
    difference over ``+- half_window_s`` (``h`` rows at the nominal rate), NaN where a row
    ``h`` before or after is missing, beyond the ends, or across a gap (more than 1.5 times
    the window apart). rad/s."""
    h = max(int(round(half_window_s * sample_rate_hz)), 1)
    out = np.full(np.shape(angle), np.nan)
    if angle.shape[0] <= 2 * h:
        return out
    span = (t[2 * h:] - t[:-2 * h]).reshape((-1,) + (1,) * (angle.ndim - 1))
    ok = (span > 0) & (span <= 1.5 * 2 * h / sample_rate_hz)
    with np.errstate(invalid="ignore", divide="ignore"):
        out[h:-h] = np.where(ok, (angle[2 * h:] - angle[:-2 * h]) / np.where(ok, span, 1.0),
                             np.nan)
    return out


def _legendre(x: np.ndarray, degree: int) -> list[np.ndarray]:
    p = [np.ones_like(x), x]
    for n in range(1, degree):
        p.append(((2 * n + 1) * x * p[n] - n * p[n - 1]) / (n + 1))
    return p[1:degree + 1]


class ErrorParts(eqx.Module):
    """One angle's error decomposition (``diagnostics``): ``e = estimate - truth`` regressed
    on every group of ``GROUPS`` at once (the module docstring).

    ``count``: rows used; ``rms_deg``: the error's RMS; ``rest_deg``: the residual's RMS;
    ``bias_deg``: the intercept (the mean error: every other regressor is centred);
    ``clock_offset_ms``: the rate's coefficient ``c`` (``e ~ c rate``: the estimate runs
    ``c`` ahead of motion capture, ``estimate(t) ~ truth(t + c)``; negative: behind);
    ``play_deg``: the direction's coefficient (the estimate reads ``+play`` while the angle
    grows and ``-play`` while it shrinks; negative: it trails the motion, as behind a
    backlash of half-width ``|play|``); ``drift_deg`` and
    ``clock_deg``: the RMS of the ``time`` group's two parts, its polynomials in time and
    ``c rate``. Per group (``{group: value}``): ``part_deg`` the RMS of its fitted
    component, ``share`` the part of the mean square error it removes when added last, ``f``
    the drop-one F statistic on ``n_eff`` effective rows (the module docstring) and ``f95``
    its 95 % point, ``F(q, n_eff - p)`` for ``q`` of the ``p`` regressors (``None`` where
    ``n_eff`` leaves no degrees of freedom); ``significant``: ``f > f95`` and ``part_deg >=
    PRACTICAL_DEG``."""

    angle: str
    count: int
    rms_deg: float
    rest_deg: float
    bias_deg: float
    clock_offset_ms: float
    play_deg: float
    drift_deg: float
    clock_deg: float
    part_deg: Mapping[str, float]
    share: Mapping[str, float]
    f: Mapping[str, float | None]
    f95: Mapping[str, float | None]
    n_eff: Mapping[str, float]
    significant: Mapping[str, bool]


def _design(rate, truth, tau) -> tuple[np.ndarray, list[str], list[str]]:
    """The regressors (columns), each column's group and name."""
    direction = np.where(np.abs(rate) < DEAD_ZONE_RAD_S, 0.0, np.sign(rate))
    lo, hi = truth.min(), truth.max()
    x = 2.0 * (truth - lo) / (hi - lo) - 1.0 if hi > lo else np.zeros_like(truth)
    cols = ([np.ones_like(rate), direction] + _legendre(x, 3) + _legendre(tau, 2) + [rate])
    groups = ["bias", "direction", "angle", "angle", "angle", "time", "time", "time"]
    names = ["intercept", "direction", "P1(angle)", "P2(angle)", "P3(angle)", "P1(time)",
             "P2(time)", "rate"]
    return np.stack(cols, axis=1), groups, names


def error_parts(sessions: Sequence[Session], angles: Sequence[np.ndarray],
                burn_in_s: float = 0.0) -> tuple[ErrorParts, ...]:
    """Every angle's ``ErrorParts`` from ``angles`` (each session's ``(T, K)`` estimate,
    rad) against each session's ``truth()``, pooled over sessions. Rows where truth, the
    estimate or its rate is missing are left out, and the first ``burn_in_s`` of every
    session; an angle with fewer than ``MIN_ROWS`` rows is not reported."""
    robot = sessions[0].robot
    out = []
    for k, name in enumerate(robot.angle_names):
        rows, per = [], []  # pooled regressors; per session (T, used rows)
        for s, a in zip(sessions, angles):
            est = np.asarray(a, np.float64)[:, k]
            truth = s.truth()[:, k]
            rate = angle_rate(s.t, est, sample_rate_hz=s.sample_rate_hz)
            span = max(s.t[-1] - s.t[0], 1e-9)
            tau = 2.0 * (s.t - s.t[0]) / span - 1.0
            ok = np.isfinite(est) & np.isfinite(truth) & np.isfinite(rate)
            ok &= s.t - s.t[0] >= burn_in_s
            rows.append(np.stack([est - truth, rate, truth, tau], axis=1)[ok])
            per.append((s.t.shape[0], np.flatnonzero(ok)))
        data = np.concatenate(rows)
        if data.shape[0] < MIN_ROWS:
            continue
        e = data[:, 0]
        X, groups, cols = _design(data[:, 1], data[:, 2], data[:, 3])
        # Centred (so that the intercept is the mean error) and scaled to unit RMS (for the
        # conditioning of the solve); a column that does not vary (an angle never moving) is
        # left out.
        X[:, 1:] -= X[:, 1:].mean(axis=0)
        scale = np.sqrt(np.mean(X**2, axis=0))
        use = scale > 1e-12 * np.maximum(1.0, np.abs(X).max(axis=0))
        X, scale = X[:, use] / scale[use], scale[use]
        groups = [g for g, u in zip(groups, use) if u]
        cols = [c for c, u in zip(cols, use) if u]
        beta, fit = least_squares(X, e)
        rss = float(np.sum((e - fit) ** 2))
        ms = float(np.mean(e**2))
        n, p = e.shape[0], X.shape[1]
        noise = noise_model(_pieces(e - fit, per))
        part, share, f, f95, n_eff, sig = {}, {}, {}, {}, {}, {}
        for g in GROUPS:
            idx = [i for i, x in enumerate(groups) if x == g]
            if not idx:
                part[g], share[g], f[g], f95[g], n_eff[g], sig[g] = 0.0, 0.0, None, None, n, False
                continue
            rest = [i for i in range(p) if i not in idx]
            _, fit_without = least_squares(X[:, rest], e)
            drop = max(float(np.sum((e - fit_without) ** 2)) - rss, 0.0)
            part[g] = _deg(np.sqrt(np.mean((X[:, idx] @ beta[idx]) ** 2)))
            share[g] = drop / ms / n if ms > 0 else 0.0
            n_eff[g] = n / variance_inflation(noise, _pieces(fit - fit_without, per))
            d2 = n_eff[g] - p
            if d2 >= 1.0:
                f[g] = drop / len(idx) / max(rss / d2, 1e-300)
                f95[g] = f_quantile(0.95, len(idx), d2)
            else:
                f[g] = f95[g] = None
            sig[g] = bool(f[g] is not None and f[g] > f95[g] and part[g] >= PRACTICAL_DEG)
        coef = dict(zip(cols, beta / scale))
        slow = [i for i, c in enumerate(cols) if c.endswith("(time)")]
        clock = [i for i, c in enumerate(cols) if c == "rate"]
        out.append(ErrorParts(
            angle=name, count=n, rms_deg=_deg(np.sqrt(ms)), rest_deg=_deg(np.sqrt(rss / n)),
            bias_deg=_deg(coef.get("intercept", 0.0)),
            clock_offset_ms=1e3 * coef.get("rate", 0.0),
            play_deg=_deg(coef.get("direction", 0.0)),
            drift_deg=_deg(np.sqrt(np.mean((X[:, slow] @ beta[slow]) ** 2))),
            clock_deg=_deg(np.sqrt(np.mean((X[:, clock] @ beta[clock]) ** 2))),
            part_deg=part, share=share, f=f, f95=f95, n_eff=n_eff, significant=sig))
    return tuple(out)


def _deg(x) -> float:
    return float(np.degrees(x))


def _pieces(values: np.ndarray, per) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pooled rows back on each session's row grid: ``(x, ok)`` per session."""
    out, start = [], 0
    for n_rows, idx in per:
        x, ok = np.zeros(n_rows), np.zeros(n_rows, bool)
        x[idx], ok[idx] = values[start:start + idx.size], True
        out.append((x, ok))
        start += idx.size
    return out


# ---------------------------------------------------------------------------- the result
class Diagnostics(eqx.Module):
    """What ``diagnostics`` found for one method: ``whiteness`` (one ``Whiteness`` per
    innovation channel, of the filter's innovations) and ``errors`` (one ``ErrorParts`` per
    angle, of the estimates given: ``decomposed`` says which, ``"filtered"`` or
    ``"smoothed"``, from the estimates' ``path``; ``"estimates"`` for bare arrays).
    ``to_json()``: the ``"diagnostics"`` entry of ``kckf evaluate --json``."""

    method: str
    decomposed: str
    lags: int
    whiteness: tuple[Whiteness, ...]
    errors: tuple[ErrorParts, ...]

    def to_json(self) -> dict:
        """The JSON form (plain types; numbers rounded to what they can say)."""
        white = {w.channel: {
            "count": w.count, "mean": _r(w.mean, 3), "nis": _r(w.nis, 3),
            "acf": [_r(x, 3) for x in w.acf], "band": _r(float(np.max(w.band)), 4),
            "q": _r(w.q, 1), "q95": _r(w.q95, 2), "white": w.white, "outside": list(w.outside),
        } for w in self.whiteness}
        errors = {p.angle: {
            "count": p.count, "rms_deg": _r(p.rms_deg, 3), "rest_deg": _r(p.rest_deg, 3),
            "bias_deg": _r(p.bias_deg, 3), "clock_offset_ms": _r(p.clock_offset_ms, 1),
            "play_deg": _r(p.play_deg, 3), "drift_deg": _r(p.drift_deg, 3),
            "clock_deg": _r(p.clock_deg, 3),
            "groups": {g: {"part_deg": _r(p.part_deg[g], 3), "share": _r(p.share[g], 3),
                           "f": _r(p.f[g], 2), "f95": _r(p.f95[g], 2),
                           "n_eff": _r(p.n_eff[g], 1), "significant": p.significant[g]}
                       for g in GROUPS},
        } for p in self.errors}
        return {"decomposed": self.decomposed, "whiteness_of": "filter innovations",
                "lags": self.lags, "whiteness": white, "errors": errors}

    def summary(self) -> list[str]:
        """A line or two for people (``describe`` of ``to_json()``)."""
        return describe(self.method, self.to_json())


def _r(x, digits: int):
    if x is None or not math.isfinite(float(x)):
        return None
    return round(float(x), digits)


def describe(method: str, doc: Mapping) -> list[str]:
    """One line about the innovations' whiteness and one about the significant error parts,
    from ``Diagnostics.to_json()``'s form."""
    white = doc["whiteness"]
    lines = []
    if white:
        bad = [c for c, w in white.items() if not w["white"]]
        lines.append(f"{method}: innovations white in {len(white) - len(bad)} of {len(white)} "
                     "channel(s)" + (f"; not white: {', '.join(bad)}" if bad else ""))
    found = []
    for angle, p in doc["errors"].items():
        parts = []
        for g, x in p["groups"].items():
            if x["significant"]:
                what = {"direction": f" (play {p['play_deg']:+.2f} deg)",
                        "time": f" (clock {p['clock_offset_ms']:+.0f} ms)"}.get(g, "")
                parts.append(f"{g} {x['part_deg']:.2f}{what}")
        if parts:
            found.append(f"{angle} " + ", ".join(parts))
    lines.append(f"{method}: {doc['decomposed']} error, significant parts (deg): "
                 + ("; ".join(found) if found else "none"))
    return lines


def session_innovations(sessions: Sequence[Session], method: str,
                        params: Params | None = None, gaps: GapPolicy = GapPolicy(),
                        faults=None) -> list:
    """Each session's fused Hall innovations ``(nu, var, valid)`` (NumPy float64, ``T Nb m``)
    under ``method``, restarted where ``gaps`` restarts the filter (``faults``: the fault
    policy, as ``filter_sessions``')."""
    out = []
    for s, p in zip(sessions, session_params(sessions, params, faults=faults)):
        parts = [[np.asarray(x, np.float64) for x in
                  _innovations(p, session_series(piece, p.log_q.dtype), method)]
                 for piece in split_at_gaps(s, gaps)]
        out.append(tuple(np.concatenate(x) for x in zip(*parts)))
    return out


@eqx.filter_jit
def _innovations(params, series, method):
    return _step_innovations(params, series, method)


def diagnostics(sessions: Sequence[Session], estimates: Sequence, innovations:
                Sequence | None = None, params: Params | None = None,
                method: str | AbstractModel = "kckf", lags: int = 20,
                gaps: GapPolicy = GapPolicy(), burn_in_s: float = 0.0) -> Diagnostics:
    """Where a Kalman filter's error comes from, on recorded sessions (docs/diagnostics.md):
    the whiteness of its normalised innovations and the decomposition of its estimates'
    error against motion capture.

    Args:
        sessions: sessions with motion capture (one robot).
        estimates: each session's ``Estimate`` (from ``filter_sessions``, ``run_filter``,
            ``smooth``) or ``(T, K)`` angles in rad.
        innovations: each session's ``(nu, var, valid)`` (``T Nb m``), where they were
            computed already; else the filter ``method`` runs again for them.
        params: the parameters (``None``: each session's ``session_params``).
        method: the Kalman method (``"kckf"``, ``"kf"``, ``"kckf3d"``) whose innovations
            are judged; another method (a baseline: ``"hall_l"``, ...) has none, and only its
            error is decomposed.
        lags: the autocorrelation's lags ``1..lags``, and the Ljung-Box statistic's.
        gaps: where the filter restarts (its innovations restart too).
        burn_in_s: the first seconds of every session are left out of both.

    Returns:
        a ``Diagnostics``.

    Example:
        >>> import kckf_jax as kk
        >>> s = kk.simulate("x,y", "cyclic", seed=1, duration_s=20)
        >>> d = kk.diagnostics([s], kk.filter_sessions([s], "kckf"))
        >>> sorted(d.to_json())
        ['decomposed', 'errors', 'lags', 'whiteness', 'whiteness_of']
    """
    method = method_name(method)
    if not sessions:
        raise ValueError("diagnostics: no sessions")
    if len(estimates) != len(sessions):
        raise ValueError(f"diagnostics: {len(estimates)} estimates for {len(sessions)} "
                         "sessions")
    if int(lags) < 1:
        raise ValueError(f"diagnostics: lags must be at least 1, got {lags}")
    paths = [getattr(e, "path", None) for e in estimates]
    angles = [np.asarray(getattr(e, "angles", e), np.float64) for e in estimates]
    decomposed = ("estimates" if any(x is None for x in paths) else
                  "smoothed" if all(x.startswith("smoothed") for x in paths) else "filtered")
    if innovations is None and model_of(method).kalman:
        innovations = session_innovations(sessions, method, params, gaps)
    white = ()
    if innovations is not None:
        innovations = [tuple(np.asarray(x, np.float64) for x in inn) for inn in innovations]
        nu0 = innovations[0][0]
        names = channel_names(sessions[0].robot, method, nu0.shape[1], nu0.shape[2])
        pieces = [segments(s.n_steps, find_gaps(s.t, gaps)) for s in sessions]
        keep = [s.t - s.t[0] >= burn_in_s for s in sessions]
        order = sessions[0].robot.angle_names
        white = tuple(sorted(whiteness(innovations, pieces, names, int(lags), keep),
                             key=lambda w: order.index(w.channel) if w.channel in order
                             else len(order)))
    return Diagnostics(method=method, decomposed=decomposed, lags=int(lags), whiteness=white,
                       errors=error_parts(sessions, angles, burn_in_s))


def consistency_figures(sessions: Sequence[Session], method: str | AbstractModel, estimates,
                        params: Params | None = None, gaps: GapPolicy = GapPolicy(),
                        innovations: Sequence | None = None
                        ) -> tuple[dict, list[np.ndarray]]:
    """The Kalman filters' consistency on ``sessions``: ``{"nis": ..., "nees": ...}``
    (``_likelihood.consistency``: the mean normalised innovation squared of the fused Hall
    readings with the 95 % interval of a consistent filter's mean, and the mean normalised
    squared error of the angles where motion capture exists, whose terms are correlated in
    time so that it has no such interval), and each session's
    per-row mean NIS (NaN where no reading was used) for the plots. The innovations are the
    filter's own: across a gap where ``gaps`` restarts the filter, they restart too.
    ``innovations``: ``session_innovations``' result, where it was computed already."""
    method = method_name(method)
    if innovations is None:
        innovations = session_innovations(sessions, method, params, gaps)
    nis_all, nees_all, rows = [], [], []
    for s, e, (nu, var, valid) in zip(sessions, estimates, innovations):
        valid = (valid > 0) & (var > 0)
        nis = np.where(valid, nu**2 / np.where(valid, var, 1.0), np.nan)
        nis_all.append(nis[np.isfinite(nis)])
        flat = nis.reshape(nis.shape[0], -1)
        used = np.isfinite(flat).sum(axis=1)  # rows with no reading used: NaN, no warning
        rows.append(np.where(used > 0, np.nansum(flat, axis=1) / np.maximum(used, 1), np.nan))
        std = np.asarray(e.angle_std, np.float64)
        err = (np.asarray(e.angles, np.float64) - s.truth()) / np.where(std > 0, std, np.nan)
        nees_all.append(err[np.isfinite(err)] ** 2)
    return ({"nis": consistency(np.concatenate(nis_all)),
             "nees": consistency(np.concatenate(nees_all), independent=False)}, rows)
