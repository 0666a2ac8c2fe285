"""The one process-wide setting kckf-jax offers, made only when asked (``enable_cpu_loops``):
XLA's CPU while loops compiled as one kernel each. Its parsing of ``XLA_FLAGS``, every state
it reports, that importing the package changes nothing in the process, and that the filters'
loops (forward and reverse) are ones XLA takes under it."""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax._paths import _cpu_loops as cl

OPTION = cl.OPTION


def test_with_option_adds_to_the_flags_and_to_existing_extra_options():
    assert cl.with_option("", 5) == f"--xla_backend_extra_options={OPTION}=5"
    assert cl.with_option("--xla_dump_to=/tmp/d", 5) == (
        f"--xla_dump_to=/tmp/d --xla_backend_extra_options={OPTION}=5")
    # XLA keeps one value per flag: the option joins the last list rather than replacing it.
    got = cl.with_option("--xla_backend_extra_options=a=1 --x=2 "
                         "--xla_backend_extra_options=b=2,c=3 --y=4", 7)
    assert got == ("--xla_backend_extra_options=a=1 --x=2 "
                   f"--xla_backend_extra_options=b=2,c=3,{OPTION}=7 --y=4")
    assert cl.with_option("--xla_backend_extra_options=", 7) == (
        f"--xla_backend_extra_options={OPTION}=7")
    assert cl.preset_bytes(got) == 7
    assert cl.preset_bytes("--xla_backend_extra_options=a=1") is None


def test_library_fusions_are_turned_off_only_where_jaxlib_has_the_flag():
    """An unknown flag aborts XLA, so the YNNPACK flag goes only to the releases known to have
    it (the ones pyproject.toml allows), and never twice or over a user's own value."""
    flag = cl.YNN_FLAG
    assert cl.without_ynn("--x=1", (0, 10, 2)) == f"--x=1 {flag}=-reduce"
    assert cl.without_ynn("", (0, 12, 0, 1)) == f"{flag}=-reduce"
    for older_or_newer in [(0, 10, 1), (0, 9, 2), (0, 13), (1, 0, 0), None]:
        assert cl.without_ynn("--x=1", older_or_newer) == "--x=1"
    mine = f"--x=1 {flag}=reduce"
    assert cl.without_ynn(mine, (0, 11, 0)) == mine
    version = cl.jaxlib_version()
    assert version is not None and version[:3] == tuple(
        int(x) for x in jax.lib.__version__.split(".")[:3])


def test_enable_reports_every_state_and_changes_only_what_it_says():
    env = {"XLA_FLAGS": "--xla_dump_to=/tmp/d"}
    state = cl.enable_cpu_loops(env)
    assert state.state == "on" and state.loop_bytes == cl.LOOP_BYTES
    assert cl.preset_bytes(env["XLA_FLAGS"]) == cl.LOOP_BYTES
    assert env["XLA_FLAGS"].startswith("--xla_dump_to=/tmp/d ")
    assert env["XLA_FLAGS"].endswith(f" {cl.YNN_FLAG}=-reduce")  # this jaxlib has it
    assert cl.YNN_FLAG in state.detail
    mine = {"XLA_FLAGS": f"{cl.YNN_FLAG}=reduce"}  # a user's own value: kept, not claimed
    assert cl.YNN_FLAG not in cl.enable_cpu_loops(mine).detail
    assert mine["XLA_FLAGS"].startswith(f"{cl.YNN_FLAG}=reduce ")

    again = dict(env)  # a subprocess inherits the flags: kept as they are
    assert cl.enable_cpu_loops(again).state == "preset"
    assert again == env

    env = {"KCKF_XLA_LOOPS": "4096"}
    assert cl.enable_cpu_loops(env)[:2] == ("on", 4096)
    assert cl.preset_bytes(env["XLA_FLAGS"]) == 4096

    env = {"KCKF_XLA_LOOPS": "0", "XLA_FLAGS": "--x=1"}
    off = cl.enable_cpu_loops(env)
    assert off.state == "off" and off.loop_bytes == cl.XLA_DEFAULT_BYTES
    assert env == {"KCKF_XLA_LOOPS": "0", "XLA_FLAGS": "--x=1"}

    with pytest.raises(ValueError, match="KCKF_XLA_LOOPS='fast'.*0 .*bytes"):
        cl.enable_cpu_loops({"KCKF_XLA_LOOPS": "fast"})


_CLEAN_ENV = {k: v for k, v in os.environ.items() if k not in ("KCKF_XLA_LOOPS", "XLA_FLAGS")}


def _python(code: str) -> str:
    got = subprocess.run([sys.executable, "-c", code], env=_CLEAN_ENV, capture_output=True,
                         text=True, timeout=120)
    assert got.returncode == 0, got.stderr[-3000:]
    return got.stdout.strip()


def test_importing_the_package_changes_nothing_in_the_process():
    """Every module of the package imported: the environment (``XLA_FLAGS`` included) and
    JAX's configuration are as they were, and JAX's backend has not started (``enable_cpu_loops``
    could still take effect)."""
    code = ("import os, jax, pkgutil, importlib\n"
            "env, conf = dict(os.environ), dict(jax.config.values)\n"
            "import kckf_jax\n"
            "for m in pkgutil.walk_packages(kckf_jax.__path__, 'kckf_jax.'):\n"
            "    if not m.name.endswith('__main__'):\n"
            "        importlib.import_module(m.name)\n"
            "assert dict(os.environ) == env, set(os.environ.items()) ^ set(env.items())\n"
            "assert dict(jax.config.values) == conf\n"
            "print(kckf_jax.enable_cpu_loops().state)\n"
            "print(kckf_jax.cpu_loops().one_kernel)\n")
    assert _python(code).splitlines() == ["on", "True"]


def test_no_private_jax_module_is_used():
    root = pathlib.Path(kk.__file__).parent
    users = [str(f.relative_to(root)) for f in root.rglob("*.py") if "jax._src" in f.read_text()]
    assert users == []


def test_a_late_call_says_so_and_how_to_fix_it():
    """Called after the first computation, the setting cannot reach XLA: where this XLA does
    not compile loops as one kernel by itself (jax 0.10), ``cpu_loops`` says "late" and what to
    do; where it does (jax 0.12), the loops are one kernel anyway."""
    code = ("import jax.numpy as jnp, kckf_jax as kk\n"
            "jnp.zeros(3).block_until_ready()\n"
            "print(kk.enable_cpu_loops().state)\n"
            "r = kk.cpu_loops()\n"
            "print(r.state, r.one_kernel)\n"
            "print(r.detail)\n")
    enabled, report, detail = _python(code).splitlines()
    assert enabled == "on"
    assert report in ("late False", "on True")
    if report.startswith("late"):
        assert "before the process's first JAX computation" in detail


def _loops(compiled_text: str) -> tuple[int, int]:
    """(while loops, loops hoisted as one kernel) in a compiled program's text."""
    whiles = len(re.findall(r"= \(.*\) while\(", compiled_text))
    hoisted = compiled_text.count('xla_cpu_small_call="true"')
    return whiles, hoisted


@pytest.mark.parametrize("method,path", [("kckf", "lanes"), ("kckf", "sequential"),
                                         ("kckf3d", "lanes")])
@pytest.mark.long
def test_the_filters_loops_forward_and_reverse_are_each_one_kernel(method, path):
    """Under the setting (the suite's conftest makes the call), every while loop of the
    fitting gradient is hoisted: a dot, scatter, custom call or library (YNNPACK) fusion in a
    step would keep its loop on the thunk runtime, 2-4x slower (benchmarks/README.md,
    cpu_loops.py; ``kckf3d``'s reverse pass has reductions XLA hands to YNNPACK unless the
    setting turns that off)."""
    if not kk.cpu_loops().one_kernel:
        pytest.skip(f"loops are not one kernel here: {kk.cpu_loops().detail}")
    robot = kk.Robot.from_spec("x,y,x,y" if method == "kckf" else "xyz,xyz")
    # 16 lanes: on fewer XLA's cost model keeps the reductions out of YNNPACK anyway.
    trials = [kk.simulate(robot, "human", seed=s, duration_s=0.6, drop_prob=0.05)
              for s in range(2 if method == "kckf" else 16)]
    batch = kk.make_batch(trials, jnp.float32)
    params = kk.initial_params(trials, kk.FitConfig(), jnp.float32)
    diff, static = eqx.partition(params, eqx.is_array)
    grad = jax.jit(jax.grad(lambda d: kk.loss_fn(eqx.combine(d, static), batch, method,
                                                 path=path)))
    whiles, hoisted = _loops(grad.lower(diff).compile().as_text())
    assert whiles >= 2 and hoisted == whiles
    assert np.all(np.isfinite(np.asarray(jax.tree_util.tree_leaves(grad(diff))[0])))
