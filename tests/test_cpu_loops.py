"""The one process-wide setting kckf-jax makes on import (``_cpu_loops``): XLA's CPU while loops
compiled as one kernel each. Its parsing of ``XLA_FLAGS``, every state it reports, and that the
filters' loops (forward and reverse) are ones XLA takes under it."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kckf_jax as kk
from kckf_jax import _cpu_loops as cl

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


def test_configure_reports_every_state_and_changes_only_what_it_says():
    env = {"XLA_FLAGS": "--xla_dump_to=/tmp/d"}
    state = cl.configure(env, started=lambda: False)
    assert state.state == "on" and state.loop_bytes == cl.LOOP_BYTES
    assert cl.preset_bytes(env["XLA_FLAGS"]) == cl.LOOP_BYTES
    assert env["XLA_FLAGS"].startswith("--xla_dump_to=/tmp/d ")

    again = dict(env)  # a subprocess inherits the flags: kept as they are
    assert cl.configure(again, started=lambda: False).state == "preset"
    assert again == env

    env = {"KCKF_XLA_LOOPS": "4096"}
    assert cl.configure(env, started=lambda: False)[:2] == ("on", 4096)
    assert cl.preset_bytes(env["XLA_FLAGS"]) == 4096

    env = {"KCKF_XLA_LOOPS": "0", "XLA_FLAGS": "--x=1"}
    off = cl.configure(env, started=lambda: False)
    assert off.state == "off" and off.loop_bytes == cl.XLA_DEFAULT_BYTES
    assert env == {"KCKF_XLA_LOOPS": "0", "XLA_FLAGS": "--x=1"}

    with pytest.raises(ValueError, match="KCKF_XLA_LOOPS='fast'.*0 .*bytes"):
        cl.configure({"KCKF_XLA_LOOPS": "fast"}, started=lambda: False)


def test_a_late_import_changes_nothing_and_says_how_to_fix_it():
    env = {}
    with pytest.warns(UserWarning, match="before kckf_jax was imported.*Import kckf_jax before"):
        late = cl.configure(env, started=lambda: True)
    assert late.state == "late" and late.loop_bytes == cl.XLA_DEFAULT_BYTES
    assert env == {}  # XLA has read its flags: nothing to change
    assert "XLA_FLAGS='--xla_backend_extra_options=" in late.detail
    # Opted out, or set by the user: no warning.
    assert cl.configure({"KCKF_XLA_LOOPS": "0"}, started=lambda: True).state == "off"
    flags = {"XLA_FLAGS": f"--xla_backend_extra_options={OPTION}=9"}
    assert cl.configure(flags, started=lambda: True).state == "preset"


def test_importing_the_package_starts_no_backend():
    """The setting takes effect only if no module of the package starts JAX's backend when it
    is imported (XLA reads its flags then)."""
    code = ("import pkgutil, importlib, kckf_jax\n"
            "from jax._src import xla_bridge\n"
            "for m in pkgutil.walk_packages(kckf_jax.__path__, 'kckf_jax.'):\n"
            "    if not m.name.endswith(('export_loader', '__main__')):\n"
            "        importlib.import_module(m.name)\n"
            "assert not xla_bridge.backends_are_initialized()\n"
            "print(kckf_jax.cpu_loops().state)\n")
    env = {k: v for k, v in os.environ.items() if k != "KCKF_XLA_LOOPS"}
    env["XLA_FLAGS"] = os.environ.get("KCKF_TEST_XLA_FLAGS", "")
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    expect = "preset" if cl.preset_bytes(env["XLA_FLAGS"]) is not None else "on"
    assert got.stdout.strip() == expect


def _loops(compiled_text: str) -> tuple[int, int]:
    """(while loops, loops hoisted as one kernel) in a compiled program's text."""
    whiles = len(re.findall(r"= \(.*\) while\(", compiled_text))
    hoisted = compiled_text.count('xla_cpu_small_call="true"')
    return whiles, hoisted


@pytest.mark.parametrize("path", ["lanes", "sequential"])
def test_the_filters_loops_forward_and_reverse_are_each_one_kernel(path):
    """Under the setting (this process imported kckf_jax with it), every while loop of the
    fitting gradient is hoisted: a dot, scatter or custom call in a step would keep its loop
    on the thunk runtime, 2-4x slower (benchmarks/README.md, cpu_loops.py)."""
    if kk.cpu_loops().loop_bytes < cl.LOOP_BYTES:
        pytest.skip(f"the setting is not in effect here: {kk.cpu_loops().detail}")
    robot = kk.Robot.from_spec("x,y,x,y")
    trials = [kk.simulate(robot, "human", seed=s, duration_s=0.6, drop_prob=0.05)
              for s in range(2)]
    batch = kk.make_batch(trials, jnp.float32)
    params = kk.initial_params(trials, kk.FitConfig(), jnp.float32)
    diff, static = eqx.partition(params, eqx.is_array)
    grad = jax.jit(jax.grad(lambda d: kk.loss_fn(eqx.combine(d, static), batch, path=path)))
    whiles, hoisted = _loops(grad.lower(diff).compile().as_text())
    assert whiles >= 2 and hoisted == whiles
    assert np.all(np.isfinite(np.asarray(jax.tree_util.tree_leaves(grad(diff))[0])))
