"""Eq. 1 written once (``_hall``): its NumPy form (the host's checks and reports), its JAX
forms (the filters, the monitor's angle and slope from one pair of exponentials) and its
inverse (the simulator) agree (issue 48, item 2)."""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np

from kckf_jax import Params, Robot, hall_angle, hall_slope, hall_voltage
from kckf_jax._models._hall import hall_angle_and_slope, hall_angle_np, hall_exponentials


def _curves(seed=0):
    robot = Robot.from_spec("x,y,xyz")
    params = Params.paper_defaults(robot, dtype=jnp.float64)
    rng = np.random.default_rng(seed)
    coeffs = [np.asarray(c, np.float64) * (rng.uniform(0.8, 1.25, np.shape(c))
                                            if i < 4 else 1.0)
              for i, c in enumerate(params.hall_coeffs)]
    return coeffs, rng.uniform(0.2, 3.1, (200, robot.n_hall))


def test_the_numpy_form_is_the_jax_form():
    coeffs, v = _curves()  # float64 (tests/conftest.py)
    want = np.asarray(hall_angle(jnp.asarray(v), *(jnp.asarray(c) for c in coeffs)))
    np.testing.assert_allclose(hall_angle_np(v, coeffs), want, rtol=1e-12, atol=1e-15)
    w, k = hall_exponentials(*coeffs)
    angle, slope = hall_angle_and_slope(jnp.asarray(v), w, k)
    np.testing.assert_array_equal(np.asarray(angle), want)
    np.testing.assert_allclose(
        np.asarray(slope),
        np.abs(np.asarray(hall_slope(jnp.asarray(v), *(jnp.asarray(c) for c in coeffs)))),
        rtol=1e-12)


def test_missing_and_overflow_stay_quiet_and_the_inverse_returns_the_voltage():
    coeffs, v = _curves(1)
    v[3, 2] = np.nan
    v[4, 1] = 500.0  # e^(b V) overflows
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = hall_angle_np(v, coeffs)
    assert np.isnan(out[3, 2]) and np.isinf(out[4, 1])
    good = np.isfinite(out)
    back = hall_voltage(np.where(good, out, 0.0), *coeffs)
    np.testing.assert_allclose(back[good], v[good], atol=1e-9)


def test_no_other_module_writes_the_exponentials():
    import re
    from pathlib import Path

    import kckf_jax

    root = Path(kckf_jax.__file__).parent
    by_hand = re.compile(r"exp\(\s*(k1|k2|-?\s*d\b|b\b)\s*\*")
    found = [f"{f.relative_to(root)}:{n}" for f in root.rglob("*.py") if f.name != "_hall.py"
             for n, line in enumerate(f.read_text().splitlines(), 1) if by_hand.search(line)]
    assert not found, found
