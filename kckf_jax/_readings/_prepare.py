"""The readings prepared once: a series (or a live row) turned into the filter's typed input.

Three types mark how far a series has come, so no flag records it:

* ``SensorSeries`` (the kernel's): the readings as recorded or received;
* ``ScreenedSeries``: judged, each reading alone (``_screen.screen``: out of range, railed,
  unreachable, saturated) and each sensor over time (``_health``: noisy, stuck, clipped, a
  bias step; a gyro missing for a while stood in for), as ``params.faults`` says. The
  decisions depend on the Hall curves and the limits, not on what a fit learns, so a fit
  judges its batch once (``kk.screened``) and prepares it again for every parameter value;
* ``FilterInput`` (the kernel's): judged, in the filter's dtype, and with the learned sensor
  effects (``Params.effects``) taken out: what ``step`` and every path compute on.

``prepare`` makes a ``FilterInput`` of a recording or a batch from any of the three;
``prepare_row`` makes one of a lone row (a stream's packet), with the learned gyro timing
applied through the filter state's hold (``_effects.timed_hold``), as ``prepare`` applies it
over a recording's rows (``_effects.timed_gyro``), so a stream and a recording agree.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from .._models._classes import AbstractModel, exact_kinematics
from .._models._effects import corrected_readings, timed_hold
from .._models._kernel import FilterInput, FilterState, SensorSeries
from .._models._params import Params
from ._health import screened_series
from ._screen import screen


class ScreenedSeries(SensorSeries):
    """A ``SensorSeries`` (one recording ``T`` or a batch ``B T``) whose readings are judged
    (``kk.screened``): every reading the filter does not use is missing (NaN), and a gyro
    missing for a while holds its stand-in's reading. ``prepare`` does not judge it again;
    the learned sensor effects are still in its readings."""


def _cast(series, dtype):
    if dtype is None:
        return series
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x).astype(dtype), series)


def judged(params: Params, series: SensorSeries, method: str | AbstractModel = "kckf",
           dtype=None) -> tuple[ScreenedSeries, jax.Array]:
    """``series`` (a recording or a batch, not a lone row; cast to ``dtype`` when given)
    judged row by row and over time (``_health.screened_series``, as ``params.faults`` says;
    no gyro stand-ins under exact kinematics: ``exact_kinematics``), and each reading's code
    (``... T G + M``, ``_screen.FAULT_KINDS``; 0: used or missing)."""
    series = _cast(series, dtype)
    if jnp.ndim(series.dt) == 0:
        raise ValueError("judged takes a recording or a batch (a time axis); a lone row is "
                         "prepared by prepare_row")
    gyro, hall_v, codes = screened_series(params, series.dt, jnp.asarray(series.gyro),
                                          jnp.asarray(series.hall_v),
                                          exact_kinematics(method))
    return ScreenedSeries(series.dt, gyro, hall_v), codes


def prepare(params: Params, series: SensorSeries | FilterInput,
            method: str | AbstractModel = "kckf", dtype=None) -> FilterInput:
    """The filter's input from a recording or a batch: cast to ``dtype`` (when given), judged
    unless it is a ``ScreenedSeries`` already (``judged``), and the learned sensor effects of
    ``params`` taken out (``_effects.corrected_readings``; the readings as they are when no
    effect is on). A ``FilterInput`` is returned as it is (cast to ``dtype``)."""
    series = _cast(series, dtype)
    if isinstance(series, FilterInput):
        return series
    if not isinstance(series, ScreenedSeries):
        series, _ = judged(params, series, method)
    gyro, hall_v = _corrected(params, series.gyro, series.hall_v)
    return FilterInput(series.dt, gyro, hall_v)


def prepare_row(params: Params, state: FilterState, row: SensorSeries | FilterInput,
                method: str | AbstractModel = "kckf") -> tuple[FilterState, FilterInput]:
    """One lone row (a stream's packet) as the step uses it, and the state whose hold the
    prediction integrates: the row screened (``_screen.screen``: each reading alone; a
    ``ScreenedSeries`` row, judged over time by the stream's health monitor, is not screened
    again), its learned sensor effects taken out, its gyro timing applied with the hold
    (``_effects.timed_hold``). A ``FilterInput`` row is returned as it is. ``method`` is
    accepted for symmetry with ``prepare`` (a row's screen is the same for every model)."""
    del method
    if isinstance(row, FilterInput):
        return state, row
    gyro, hall_v = jnp.asarray(row.gyro), jnp.asarray(row.hall_v)
    if not isinstance(row, ScreenedSeries):
        used = screen(params, gyro, hall_v)
        gyro, hall_v = used.gyro, used.hall_v
    gyro, hall_v = _corrected(params, gyro, hall_v)
    if params.effects is not None:
        gyro = gyro.astype(state.gyro_hold.dtype)
        state = dataclasses.replace(state, gyro_hold=timed_hold(params.effects,
                                                                state.gyro_hold, gyro))
    return state, FilterInput(row.dt, gyro, hall_v)


def _corrected(params: Params, gyro, hall_v):
    effects = params.effects
    if effects is None or not effects.on:
        return gyro, hall_v
    return corrected_readings(effects, params.robot, params.hall_coeffs, jnp.asarray(gyro),
                              jnp.asarray(hall_v))
