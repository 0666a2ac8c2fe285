"""The filters as model objects (issue 48, item 1): one table of names (``kk.MODELS``), no
method name compared anywhere else, and the API taking the object wherever it takes the name
(a model registered with one line runs through every path, the smoother, a fitting step, the
stream and the export)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kckf_jax as kk

NAMES = "|".join(sorted(kk.METHODS, key=len, reverse=True))
#: A decision by a method's name: compared with a literal, a literal list of names, a name
#: list standing for a property, or a name's prefix.
BY_NAME = [re.compile(p) for p in (
    rf"""(==|!=)\s*["']({NAMES})["']""",
    rf"""["']({NAMES})["']\s*(==|!=)""",
    rf"""(?<!for )\b\w+\s+(not\s+)?in\s*[\(\[{{]\s*["']({NAMES})["']""",
    r"""\b(in|not in)\s+(KALMAN_METHODS|FILTER_METHODS)\b""",
    r"""method\.startswith\(""",
)]


def test_no_method_name_is_compared_outside_the_table():
    root = Path(kk.__file__).parent
    found = []
    for f in sorted(root.rglob("*.py")):
        rel = f.relative_to(root).as_posix()
        # The table itself; the other papers' filters have their own methods ("kf", "mkf").
        if rel == "_models/_classes.py" or rel.startswith("filters/"):
            continue
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if line.lstrip().startswith("#"):
                continue
            if any(p.search(line) for p in BY_NAME):
                found.append(f"{rel}:{n}: {line.strip()}")
    assert not found, ("decide by the model (kckf_jax._models._classes), not its name:\n"
                       + "\n".join(found))


def test_the_table_names_every_method_once_and_says_what_each_is():
    assert tuple(kk.MODELS) == kk.METHODS == ("kckf", "kf", "gyro", "hall_l", "hall_r",
                                              "kckf3d")
    assert all(kk.model_of(n).name == n for n in kk.METHODS)
    assert [n for n, m in kk.MODELS.items() if m.kalman] == ["kckf", "kf", "kckf3d"]
    assert [n for n, m in kk.MODELS.items() if not m.gyro_pairs] == ["kckf3d"]
    assert [n for n, m in kk.MODELS.items() if not m.torso] == ["hall_l", "hall_r"]
    assert kk.model_of(kk.KF()) == kk.KF() and kk.model_of("kf") == kk.KF()
    with pytest.raises(ValueError, match="unknown method 'ukf'; expected one of kckf, kf"):
        kk.model_of("ukf")
    with pytest.raises(ValueError, match="the name 'kf' is taken by KF"):

        class Other(kk.KCKF):
            name: ClassVar[str] = "kf"

        kk.register_model(Other())


def test_the_api_takes_the_object_or_its_name():
    s = kk.simulate("x,y", "cyclic", 1, 4.0)
    for model in (kk.KCKF(), kk.KF(), kk.ExactKCKF(), kk.Gyro(), kk.HallL(), kk.HallR()):
        by_name = kk.filter_sessions([s], model.name)[0]
        by_object = kk.filter_sessions([s], model)[0]
        np.testing.assert_array_equal(by_object.angles, by_name.angles, err_msg=model.name)
    params = kk.Params.paper_defaults(s.robot, s.hall_models)
    series = kk.session_series(s, np.float64)
    np.testing.assert_array_equal(kk.smooth(params, series, kk.ExactKCKF()).angles,
                                  kk.smooth(params, series, "kckf3d").angles)
    assert kk.FitConfig(method=kk.KF()).method == "kf"


def _packet(s, k) -> bytes:
    obj = {"t": float(s.t[k])}
    for names, row in ((s.robot.gyro_names, s.gyro[k]), (s.robot.hall_names, s.hall_v[k])):
        obj.update({n: None if np.isnan(v) else float(v) for n, v in zip(names, row)})
    return json.dumps(obj).encode()


class Tuned(kk.KCKF):
    """A toy model: the KCKF under its own name and label (one class, one line)."""

    name: ClassVar[str] = "kckf_tuned"
    label: ClassVar[str] = "KCKF tuned"


@pytest.mark.long  # a heavy check beside a lighter default one (the default run within 4 min)
def test_a_registered_model_runs_through_every_consumer(tmp_path):
    assert kk.register_model(Tuned()) == "kckf_tuned"
    assert kk.register_model(Tuned()) == "kckf_tuned"  # again: the same model, a no-op
    robot = kk.Robot.from_spec("x,y")
    sessions = [kk.simulate(robot, "cyclic", seed, 6.0, drop_prob=0.01) for seed in (1, 2)]
    params = kk.initial_params(sessions, kk.FitConfig(), jnp.float64)
    batch = kk.pad_series([kk.session_series(s, np.float64) for s in sessions])
    want = kk.filter_batch(params, batch, "kckf")
    for path in ("sequential", "lanes", "segments"):
        got = kk.filter_batch(params, batch, Tuned(), path=path)
        np.testing.assert_allclose(got.angles, want.angles, atol=1e-9, err_msg=path)
    np.testing.assert_allclose(kk.smooth_batch(params, batch, "kckf_tuned").angles,
                               kk.smooth_batch(params, batch, "kckf").angles, atol=1e-9)
    # A fitting step: the same loss and gradient as the KCKF's.
    fit = kk.make_batch(sessions, jnp.float64)
    loss, grad = jax.value_and_grad(kk.loss_fn)(params, fit, "kckf_tuned")
    want_loss, want_grad = jax.value_and_grad(kk.loss_fn)(params, fit, "kckf")
    assert float(loss) == pytest.approx(float(want_loss), rel=1e-12)
    np.testing.assert_allclose(grad.log_q, want_grad.log_q, rtol=1e-9)
    # The stream and the exported step.
    s = sessions[0]
    parser, streams = kk.PacketParser(robot), {}
    for model in ("kckf", Tuned()):
        f = kk.StreamingFilter(params, model)
        recs = [f.push(parser.parse(_packet(s, k))) for k in range(50)]
        streams[str(model)] = [[r[n] for n in robot.angle_names] for r in recs]
    a, b = streams.values()
    np.testing.assert_array_equal(b, a)
    size = kk.export_step(params, str(tmp_path / "step.bin"), Tuned())
    assert size > 0 and (tmp_path / "step.bin").exists()
