"""Test configuration: float64 available, runtime shape checking of the whole package.

The jaxtyping import hook must run before ``kckf_jax`` is first imported, so that every
annotated function and module field of the package is checked at call time in the tests.
"""

import os
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The tests compile at XLA's backend optimisation level 0 with XLA's CPU loop emitters in place
# of its MLIR fusion emitters, in this process and in their subprocesses: most tests compile
# far more than they run (in-process compiling was 616 of about 1,130 test-seconds), and the
# two flags compile the steady smoother's program 4.7x faster (4.2 -> 0.9 s, 9,000 rows of the
# bench robot). The programs (HLO) are the same, with no fast-math either way, and the
# tolerances unchanged. The long runs (the demo, the one-hour run, the notebooks, the recovery
# fit, the command's compile cache) get XLA's default flags, as users' programs do:
# ``helpers.default_compile_env()``, from the flags the suite was started with.
# (pytest's workers inherit the controller's environment: the flags it was started with; a
# script that sets its own flags adds $KCKF_TEST_COMPILE_FLAGS.)
# XLA aborts on a flag it does not know, so only flags of the XLA that runs are passed: the
# fusion emitters' switch is gone from jax 0.11's XLA (there the MLIR emitters are the only
# ones; the optimisation level alone is set).
_XLA_FLAGS = os.environ.setdefault("KCKF_TEST_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))


def _jax_version() -> tuple[int, ...]:
    from importlib.metadata import version

    return tuple(int(x) for x in version("jax").split(".")[:2])


os.environ["KCKF_TEST_COMPILE_FLAGS"] = "--xla_backend_optimization_level=0" + (
    " --xla_cpu_use_fusion_emitters=false" if _jax_version() < (0, 11) else "")
os.environ["XLA_FLAGS"] = f"{_XLA_FLAGS} {os.environ['KCKF_TEST_COMPILE_FLAGS']}".strip()

import jax  # noqa: E402
from jaxtyping import install_import_hook  # noqa: E402

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(__file__))

with install_import_hook("kckf_jax", "_typecheck.typechecker"):
    import importlib  # noqa: E402
    import pkgutil  # noqa: E402

    import kckf_jax  # noqa: E402, F401

    # Every module of the package, so that none escapes the hook by being imported later
    # (__main__ runs the CLI when imported).
    for _mod in pkgutil.walk_packages(kckf_jax.__path__, "kckf_jax."):
        if not _mod.name.endswith("__main__"):
            importlib.import_module(_mod.name)

# XLA's CPU loops as one kernel each, as the command and the documented API example do (no
# computation has run yet: importing the package starts nothing).
kckf_jax.enable_cpu_loops()

import tempfile  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

# The tests' own subprocesses (the CLI, fits killed and resumed, stream servers) share one
# persistent compilation cache, so that a program compiled by one is loaded by the next; this
# process compiles with float64 enabled and keeps its own in-memory cache.
_CACHE = tempfile.mkdtemp(prefix="kckf-test-jax-cache-")
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"


@pytest.fixture
def key():
    return jax.random.PRNGKey(0)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def demo_results(tmp_path_factory):
    """``kckf demo`` run once for the whole test session, as a user runs it (its own process,
    float32, the console entry point): its results.json, its output folder (``"_out"``) and
    what it printed (``"_stdout"``, ``"_stderr"``)."""
    import json
    import subprocess

    out = tmp_path_factory.mktemp("demo")
    from helpers import default_compile_env

    r = subprocess.run([sys.executable, "-m", "kckf_jax", "demo", "--out", str(out)],
                       capture_output=True, text=True, timeout=280, env=default_compile_env())
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "results.json").read_text()) | {
        "_out": str(out), "_stdout": r.stdout, "_stderr": r.stderr}
