"""Learned tuning: gradients, the training loop, checkpoints, sharding and parameter files."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from kckf_jax import (
    FitConfig,
    FitInterrupted,
    Params,
    ParamsFileError,
    Robot,
    fit,
    load_params,
    loss_fn,
    make_batch,
    params_to_dict,
    save_params,
    simulate,
    write_session,
)
from kckf_jax._fitting._fit import initial_params
from kckf_jax._fitting._train import filter_spec
from kckf_jax.cli import main

ROBOT = Robot.from_spec("x,y")


@pytest.fixture(scope="module")
def small_sessions():
    return [simulate(ROBOT, "cyclic", seed=s, duration_s=3.0, drop_prob=0.05, device_seed=1)
            for s in (1, 2)]


def _leaf_loss(params, batch, chunk=None):
    diff, static = eqx.partition(params, eqx.is_array)

    def f(*leaves):
        d = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(diff), leaves)
        return loss_fn(eqx.combine(d, static), batch, "kckf", chunk)

    return f, jax.tree_util.tree_leaves(diff)


@pytest.mark.long
def test_gradient_matches_finite_differences_float64(small_sessions):
    batch = make_batch(small_sessions, jnp.float64)
    batch = jax.tree_util.tree_map(lambda x: x[:, :120] if x.ndim >= 2 else x, batch)
    params = initial_params(small_sessions, FitConfig(), jnp.float64)
    f, leaves = _leaf_loss(params, batch)
    check_grads(f, leaves, order=1, modes=["rev"], atol=1e-6, rtol=1e-4, eps=1e-6)


def test_no_nan_gradient_with_missing_readings_and_truth(small_sessions):
    """Missing sensor readings, steps without truth, padded trials: finite loss and gradient."""
    s = small_sessions[0]
    s.hall_v[10:40, :3] = np.nan  # dropped Hall readings
    s.gyro[20:25] = np.nan  # dropped gyro packets
    s.mocap[: len(s.mocap) // 2, 0] = np.nan  # an occluded marker
    s._truth = None
    batch = make_batch([s, small_sessions[1]], jnp.float32, burn_in_s=0.5, multiple_of=4)
    assert not bool(jnp.all(batch.mask))
    params = initial_params(small_sessions, FitConfig(), jnp.float32)
    for chunk in (None, 37):
        loss, grads = eqx.filter_jit(eqx.filter_value_and_grad(
            lambda p, c=chunk: loss_fn(p, batch, "kckf", c)))(params)
        assert np.isfinite(float(loss))
        for g in jax.tree_util.tree_leaves(grads):
            assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.long
def test_remat_chunks_give_the_same_loss_and_gradient(small_sessions):
    batch = make_batch(small_sessions, jnp.float64)
    params = initial_params(small_sessions, FitConfig(), jnp.float64)
    out = [eqx.filter_jit(eqx.filter_value_and_grad(lambda p, c=c: loss_fn(p, batch, "kckf", c)))(
        params) for c in (None, 17)]
    for loss, grads in out[1:]:
        assert float(loss) == pytest.approx(float(out[0][0]), rel=1e-12)
        for a, b in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(out[0][1])):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.long
def test_fit_lowers_the_loss_and_is_deterministic(small_sessions):
    cfg = FitConfig(steps=8, learning_rate=0.05, batch_size=1, seed=3)
    a = fit(small_sessions, small_sessions[1:], cfg)
    b = fit(small_sessions, small_sessions[1:], cfg)
    assert a.best_loss_deg < a.history[0]["loss_deg"]
    for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params)):
        np.testing.assert_array_equal(x, y)
    assert [h["loss_deg"] for h in a.history] == [h["loss_deg"] for h in b.history]


@pytest.mark.long
def test_frozen_leaves_do_not_move(small_sessions):
    cfg = FitConfig(steps=3, freeze=("log_hall_a", "log_p0_angle"))
    res = fit(small_sessions, (), cfg)
    init = initial_params(small_sessions, cfg)
    np.testing.assert_array_equal(res.params.log_hall_a, init.log_hall_a)
    np.testing.assert_array_equal(res.params.log_p0_angle, init.log_p0_angle)
    assert not np.array_equal(res.params.log_hall_c, init.log_hall_c)
    with pytest.raises(ValueError, match="unknown leaf 'log_nothing'"):
        FitConfig(freeze=("log_nothing",))
    assert filter_spec(init, ("log_q",)).log_q is False


@pytest.mark.long
def test_interrupted_fit_resumes_with_nothing_lost(small_sessions, tmp_path):
    cfg = FitConfig(steps=9, checkpoint_every=2, learning_rate=0.05)
    full = fit(small_sessions, small_sessions[1:], cfg)
    ckpt = str(tmp_path / "fit.ckpt")

    def stop_after_5(rec):
        if rec["step"] == 5:
            raise KeyboardInterrupt

    with pytest.raises(FitInterrupted, match="after step 5"):
        fit(small_sessions, small_sessions[1:], cfg, checkpoint=ckpt, callback=stop_after_5)
    assert os.path.exists(ckpt)
    resumed = fit(small_sessions, small_sessions[1:], cfg, checkpoint=ckpt, resume=True)
    for x, y in zip(jax.tree_util.tree_leaves(full.params),
                    jax.tree_util.tree_leaves(resumed.params)):
        np.testing.assert_array_equal(x, y)
    assert [h["loss_deg"] for h in resumed.history] == [h["loss_deg"] for h in full.history]
    other = FitConfig(steps=9, checkpoint_every=2, learning_rate=0.01)
    with pytest.raises(ValueError, match="other sessions or settings"):
        fit(small_sessions, small_sessions[1:], other, checkpoint=ckpt, resume=True)


def test_params_file_round_trip_and_errors(tmp_path):
    robot = Robot.from_spec("xz,y")
    p = Params.from_physical(robot, angle_rw=1e-3, hall_noise="voltage")
    path = str(tmp_path / "p.json")
    save_params(p, path, {"note": "test"})
    q = load_params(path)
    assert q.robot == robot and q.hall_noise == "voltage"
    for a, b in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(q)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["format"] == "kckf-params/1" and doc["fit"] == {"note": "test"}
    assert doc["hall"]["hall1_x_l"]["unit"] == "deg"

    def broken(edit, needle):
        d = json.loads(json.dumps(params_to_dict(p)))
        edit(d)
        (tmp_path / "b.json").write_text(json.dumps(d))
        with pytest.raises(ParamsFileError, match=needle):
            load_params(str(tmp_path / "b.json"))

    broken(lambda d: d.update(format="kckf-params/9"), "format: expected 'kckf-params/1'")
    broken(lambda d: d["process_noise"]["theta1_x"].update(q_rad2_s4="big"),
           r"process_noise.theta1_x.q_rad2_s4: expected a number >= 0, got 'big'")
    broken(lambda d: d["hall"]["hall1_x_l"].update(sigma_v=-1),
           r"hall.hall1_x_l.sigma_v: expected a number >= 0")
    broken(lambda d: d["hall"].pop("hall2_y_r"), r"hall.hall2_y_r: expected an object")
    broken(lambda d: d["hall"].update(hall9_x_l={}), "hall.hall9_x_l: not a name of the robot")
    broken(lambda d: d.update(joints=[{"axes": ["w"]}]), "unknown axis 'w'")
    (tmp_path / "t.json").write_text((tmp_path / "p.json").read_text()[:200])
    with pytest.raises(ParamsFileError, match="truncated or not valid JSON"):
        load_params(str(tmp_path / "t.json"))


@pytest.mark.long
def test_cli_fit_then_filter_and_evaluate_with_params(tmp_path, capsys):
    sessions = []
    for seed in (1, 2):
        path = str(tmp_path / f"s{seed}")
        assert main(["simulate", path, "--seed", str(seed), "--duration", "4", "--joints",
                     "x,y", "--quiet"]) == 0
        sessions.append(path)
    out = str(tmp_path / "p.json")
    figs = str(tmp_path / "figs")
    assert main(["fit", sessions[0], "--val", sessions[1], "-o", out, "--steps", "4",
                 "--plot", figs, "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["params"] == out and summary["selected_on"] == "val"
    # The fit's progress: every step's training loss, the validation loss where computed
    # (the first and last steps at least), and the figure of both.
    prog = summary["progress"]
    assert prog["unit"] == "deg" and prog["updates"] == list(range(summary["steps_done"]))
    assert len(prog["train"]) == len(prog["val"]) == 4
    assert all(x > 0 for x in prog["train"]) and prog["val"][0] is not None
    assert prog["val"][-1] is not None
    # The kept parameters: the best validation loss scored, here or after the last update.
    scored = {u: v for u, v in zip(prog["updates"], prog["val"]) if v is not None}
    assert summary["best_rmse_deg"] <= min(scored.values()) + 1e-9
    if summary["best_step"] in scored:
        assert summary["best_rmse_deg"] == pytest.approx(scored[summary["best_step"]])
    with open(os.path.join(figs, "fit_progress.png"), "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    assert not os.path.exists(out + ".ckpt")
    assert main(["evaluate", sessions[1], "--params", out, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["methods"]["kckf"]["mean_rmse_deg"] > 0
    assert main(["filter", sessions[1], "--params", out, "-o", str(tmp_path / "e.csv")]) == 0
    # Parameters of another robot: one line, exit 2.
    other = str(tmp_path / "other.json")
    save_params(Params.paper_defaults(Robot.from_spec("x,y,x,y")), other)
    capsys.readouterr()
    assert main(["evaluate", sessions[1], "--params", other, "--json"]) == 2
    err = capsys.readouterr().err
    assert "x,y,x,y" in err and len(err.strip().splitlines()) == 1


@pytest.mark.long
def test_sigterm_keeps_a_checkpoint_and_resume_finishes(tmp_path):
    """A real `kckf fit` process killed with SIGTERM resumes to the uninterrupted result."""
    s = str(tmp_path / "s")
    assert main(["simulate", s, "--seed", "4", "--duration", "3", "--joints", "x,y",
                 "--quiet"]) == 0
    args = [sys.executable, "-m", "kckf_jax", "fit", s, "--steps", "60", "--quiet"]
    ref = str(tmp_path / "ref.json")
    assert subprocess.run(args + ["-o", ref], capture_output=True, timeout=300).returncode == 0
    out = str(tmp_path / "p.json")
    proc = subprocess.Popen(args + ["-o", out], stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while not os.path.exists(out + ".ckpt") and time.time() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"fit ended before its first checkpoint: {proc.stderr.read()}")
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the fit finished before SIGTERM arrived")
    assert proc.returncode == 130 and "--resume" in err and os.path.exists(out + ".ckpt")
    r = subprocess.run(args + ["-o", out, "--resume"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    a, b = (json.loads(Path(p).read_text()) for p in (ref, out))
    assert a["hall"] == b["hall"] and a["process_noise"] == b["process_noise"]


SHARDING_SCRIPT = textwrap.dedent("""
    import os, json
    os.environ["XLA_FLAGS"] = ("--xla_force_host_platform_device_count=4 "
                               + os.environ.get("KCKF_TEST_COMPILE_FLAGS", ""))
    import jax
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx, jax.numpy as jnp, numpy as np
    from kckf_jax import FitConfig, fit, loss_fn, make_batch, shard_batch, simulate
    from kckf_jax._fitting._fit import initial_params
    assert jax.device_count() == 4
    sessions = [simulate("x,y", "cyclic", seed=s, duration_s=2.0, device_seed=1,
                         drop_prob=0.02) for s in range(6)]
    params = initial_params(sessions, FitConfig(), jnp.float64)
    batch = make_batch(sessions, jnp.float64, multiple_of=4)
    g = eqx.filter_jit(eqx.filter_value_and_grad(lambda p, b: loss_fn(p, b)))
    one_dev = jax.devices()[:1]
    l1, g1 = g(params, jax.device_put(batch, one_dev[0]))
    sharded = shard_batch(batch)
    assert len(sharded.truth.sharding.device_set) == 4
    l4, g4 = g(params, sharded)
    err = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
              for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g4)))
    res = fit(sessions, sessions[:2], FitConfig(steps=3), dtype=jnp.float64)
    print(json.dumps({"loss1": float(l1), "loss4": float(l4), "grad_err": err,
                      "fit_loss": res.best_loss_deg}))
""")


@pytest.mark.long
def test_sharded_over_four_devices_equals_one_device():
    r = subprocess.run([sys.executable, "-c", SHARDING_SCRIPT], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["loss4"] == pytest.approx(out["loss1"], rel=1e-12)
    assert out["grad_err"] < 1e-12
    assert np.isfinite(out["fit_loss"])


DISTRIBUTED_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    rank, port, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    if rank >= 0:  # two processes, each with its own half of the trials
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address="127.0.0.1:" + port, num_processes=2,
                                   process_id=rank)
    import equinox as eqx, jax.numpy as jnp, numpy as np
    import kckf_jax as kk
    everyone = [kk.simulate("x,y", "cyclic", seed=s, duration_s=2.0, device_seed=1,
                            drop_prob=0.02) for s in range(6)]
    mine = everyone if rank < 0 else everyone[3 * rank: 3 * rank + 3]
    val = everyone[:2] if rank < 0 else everyone[rank: rank + 1]
    params = kk.initial_params(everyone, kk.FitConfig(), jnp.float64)
    batch = kk.shard_batch(kk.make_batch(mine, jnp.float64))
    g = eqx.filter_jit(eqx.filter_value_and_grad(lambda p, b: kk.loss_fn(p, b)))
    loss, grads = g(params, batch)
    res = kk.fit(mine, val, kk.FitConfig(steps=4), dtype=jnp.float64)
    leaves = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves(grads)]
    fitted = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves(res.params)]
    json.dump({"loss": float(loss), "grads": leaves, "fitted": fitted,
               "history": res.history}, open(out, "w"))
""")


@pytest.mark.long
def test_two_processes_fit_as_one(tmp_path):
    """``jax.distributed`` with two processes on this machine (CPU collectives), each loading
    only its own trials: the loss, its gradient and a whole fit equal one process's on all
    the trials (1e-12 in float64)."""
    script = tmp_path / "dist.py"
    script.write_text(DISTRIBUTED_SCRIPT)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    procs = [subprocess.Popen([sys.executable, str(script), str(r), port,
                               str(tmp_path / f"r{r}.json")], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    one = subprocess.run([sys.executable, str(script), "-1", port, str(tmp_path / "one.json")],
                         capture_output=True, text=True, timeout=600)
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
    assert one.returncode == 0, one.stderr[-2000:]
    ref = json.loads((tmp_path / "one.json").read_text())
    for r in (0, 1):
        got = json.loads((tmp_path / f"r{r}.json").read_text())
        assert got["loss"] == pytest.approx(ref["loss"], rel=1e-12, abs=1e-15)
        for a, b in zip(got["grads"], ref["grads"]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
        # After 4 Adam steps: each step moves a leaf by up to the learning rate times
        # m/sqrt(v), which carries a gradient entry's relative rounding (the trials' sums are
        # grouped differently across the processes; near-zero entries differ by up to 1e-10
        # relative) into an absolute error of about lr x 1e-10 per step: 1.2e-11 measured on
        # a leaf of -11 (1.1e-12 relative) since every row is checkpointed.
        for a, b in zip(got["fitted"], ref["fitted"]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-10)
        for h, g in zip(ref["history"], got["history"], strict=True):
            assert set(h) == set(g)
            for k in h:
                if h[k] is None or isinstance(h[k], (str, bool)):
                    assert g[k] == h[k], k
                else:
                    assert g[k] == pytest.approx(h[k], rel=1e-12, abs=1e-15), k


@pytest.mark.long
def test_two_kckf_fit_processes_fit_as_one(tmp_path):
    """The documented multi-host launch (docs/fitting.md), on loopback: two ``kckf fit``
    processes with ``--coordinator``, each given its own session, fit as one: process 0
    writes the parameters one process writes from both sessions.

    In float64 (``--dtype float64``), so that the comparison cannot fail on rounding: the two
    launches sum the trials' gradients in another order, which changes a gradient by about
    1e-16 of its terms; Adam's step changes by at most ``lr / eps`` (0.03 / 1e-8) times that,
    under 1e-8 a step. In float32 the same order turned a small gradient's rounding into up to
    3.9e-3 of a log-parameter after three steps (once, on Python 3.12 with jax 0.12)."""
    from helpers import default_compile_env

    robot = Robot.from_spec("x,y,x,y")
    paths = []
    for seed in (1, 2):
        s = simulate(robot, "cyclic", seed=seed, duration_s=4.0, device_seed=3)
        paths.append(str(tmp_path / f"s{seed}"))
        write_session(s, paths[-1])
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = default_compile_env()
    fit = [sys.executable, "-m", "kckf_jax", "fit", "--steps", "3", "--quiet", "--dtype",
           "float64"]
    procs = [subprocess.Popen(fit + [paths[r], "-o", str(tmp_path / f"p{r}.json"),
                                     "--coordinator", f"127.0.0.1:{port}",
                                     "--num-processes", "2", "--process-id", str(r)],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for r in (0, 1)]
    one = subprocess.run(fit + paths + ["-o", str(tmp_path / "one.json")], env=env,
                         capture_output=True, text=True, timeout=600)
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
    assert one.returncode == 0, one.stderr[-3000:]
    ref = load_params(str(tmp_path / "one.json"), np.float64)
    got = load_params(str(tmp_path / "p0.json"), np.float64)  # process 0 writes
    assert not (tmp_path / "p1.json").exists()
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0.0, atol=1e-6)
