"""XLA's CPU while loops compiled as one kernel each: a process-wide setting kckf-jax makes
only when asked (``enable_cpu_loops``), never on import.

Every filter here is a ``lax.scan``, an XLA while loop. From jax 0.4.32 to 0.10, XLA's CPU
runtime ran each iteration of a loop as a sequence of "thunks", one per fused kernel, through a
dataflow executor: a filter step on lanes is 50 to 60 kernels of a few hundred numbers each,
and launching them, not their arithmetic, was most of the step's time. XLA has a pass that
compiles a whole while loop into one function (``SmallWhileLoopHoistingPass``): it takes a loop
with no dot, convolution, scatter, custom call or collective whose one iteration touches fewer
than ``xla_cpu_small_while_loop_byte_threshold`` bytes, 1,024 by default in jax 0.10, which
none of ours does. ``enable_cpu_loops`` raises that bound to ``LOOP_BYTES`` (every loop the pass
can take) in ``XLA_FLAGS``; XLA reads its flags once, when JAX's backend starts, so the call
must come before the process's first JAX computation. No per-program mechanism carries it: in
jax 0.10.2 and 0.12.0.1 ``jax.jit(..., compiler_options=...)`` refuses the option (it is an
entry of the map ``xla_backend_extra_options``).

What it gains is measured by ``python benchmarks/cpu_loops.py`` (benchmarks/README.md: on jax
0.10.2 a fitting step, the lanes filter, the smoother and the sequential filter 2.2-3.8 times
faster). jax 0.12's XLA compiles these loops as one kernel without being asked
(``cpu_loops()`` measures it), and the bound changes nothing there.

The pass also leaves alone a loop holding a library fusion: XLA's CPU backend (jax 0.10 to
0.12) hands some reductions of products (``sum(a[:, None] * b[None], axis=2)`` over a
covariance on lanes, which the exact-rotation KCKF's reverse pass and the vmapped sequential
step have) to YNNPACK as a custom fusion, and the loop around them then runs kernel by
kernel. So the call also takes reductions out of those fusions (``YNN_FLAG=-reduce`` in
``XLA_FLAGS``: XLA's own loops compute them; matrix products, as the steady path's chunks
have, stay with YNNPACK, which does them faster), where the installed jaxlib is one known to
have the flag (``YNN_JAXLIB``: an unknown flag or value aborts XLA); measured in
benchmarks/README.md (issue 49).

Who calls it: the ``kckf`` command, for itself; the README's API example, the notebooks,
``training/`` and ``benchmarks/`` show it. A library user who does not call it gets the same
results, at XLA's default speed. ``KCKF_XLA_LOOPS=0`` makes the call leave XLA's default
alone, ``KCKF_XLA_LOOPS=<bytes>`` sets that bound instead, and an ``XLA_FLAGS`` that already
names the option is kept as it is.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import MutableMapping
from typing import NamedTuple

#: XLA's option: loops whose one iteration touches fewer bytes are compiled as one kernel.
OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: The bound ``enable_cpu_loops`` sets: 1 TiB, every loop the pass can take. Smaller bounds
#: leave the larger batches' loops to the thunk runtime, which was slower there at every size
#: measured (``python benchmarks/cpu_loops.py --cases lanes_1024,lanes_4096 --bounds ...``,
#: benchmarks/README.md).
LOOP_BYTES = 1 << 40
#: The environment variable that overrides it: ``0`` for XLA's default, or a bound in bytes.
ENV = "KCKF_XLA_LOOPS"
#: XLA's own default bound in jax 0.10 (``cpu_options.cc``), for the report.
XLA_DEFAULT_BYTES = 1024

_EXTRA = "--xla_backend_extra_options="
#: XLA's flag naming the library (YNNPACK) fusions it makes on the CPU, and the value the call
#: gives it: XLA's default list without the reductions.
YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
YNN_VALUE = "-reduce"
#: The jaxlib releases known to have ``YNN_FLAG`` and its fusion type ``reduce`` (checked:
#: 0.10.2, 0.11.0, 0.12.0, 0.12.1, the versions ``pyproject.toml`` allows): from the first to
#: before the second.
YNN_JAXLIB = ((0, 10, 2), (0, 13))


class CpuLoops(NamedTuple):
    """How XLA compiles while loops on the CPU in this process.

    Attributes:
        state: what ``enable_cpu_loops`` did: ``"on"`` (it set the bound), ``"preset"``
            (``XLA_FLAGS`` already named the option; kept), ``"off"`` (``KCKF_XLA_LOOPS=0``:
            XLA's default), ``"default"`` (not called: XLA's default); and from
            ``cpu_loops()`` also ``"late"``: it set the bound after JAX's backend had started,
            so XLA never read it.
        loop_bytes: the bound in effect, in bytes per loop iteration.
        detail: the same in words, with what to do about it where something can be done.
        one_kernel: whether this process's XLA compiles a filter-sized loop as one kernel
            (measured by ``cpu_loops()``: a probe program compiled once; ``None`` where not
            measured).
    """

    state: str
    loop_bytes: int
    detail: str
    one_kernel: bool | None = None


def jaxlib_version() -> tuple[int, ...] | None:
    """The installed jaxlib's release as integers (``(0, 12, 0, 1)``), or ``None``; read from
    its metadata, without importing it."""
    from importlib import metadata

    try:
        text = metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return None
    parts = re.match(r"\d+(\.\d+)*", text)
    return tuple(int(x) for x in parts.group(0).split(".")) if parts else None


def without_ynn(flags: str, version: tuple[int, ...] | None) -> str:
    """``flags`` with reductions taken out of XLA's library fusions (``YNN_FLAG=YNN_VALUE``)
    where jaxlib ``version`` has the flag and ``flags`` does not name it already; else
    ``flags``."""
    lo, hi = YNN_JAXLIB
    if version is None or not lo <= version < hi or YNN_FLAG + "=" in flags:
        return flags
    return f"{flags} {YNN_FLAG}={YNN_VALUE}".strip()


def with_option(flags: str, loop_bytes: int) -> str:
    """``flags`` (an ``XLA_FLAGS`` value) with ``OPTION=loop_bytes`` added to its last
    ``--xla_backend_extra_options`` (a comma-separated ``key=value`` list), or that flag
    appended when there is none."""
    entry = f"{OPTION}={int(loop_bytes)}"
    found = list(re.finditer(re.escape(_EXTRA) + r"(\S*)", flags))
    if not found:
        return f"{flags} {_EXTRA}{entry}".strip()
    last = found[-1]
    value = f"{last.group(1)},{entry}" if last.group(1) else entry
    return flags[:last.start(1)] + value + flags[last.end(1):]


def preset_bytes(flags: str) -> int | None:
    """The bound that ``flags`` (an ``XLA_FLAGS`` value) sets, or ``None``."""
    found = re.findall(re.escape(OPTION) + r"=(\d+)", flags)
    return int(found[-1]) if found else None


_DEFAULT = CpuLoops("default", XLA_DEFAULT_BYTES,
                    "enable_cpu_loops() was not called: XLA's default loops (on jax 0.10, each "
                    "loop iteration kernel by kernel: the filters 2-4x slower on a CPU)")
_STATE = _DEFAULT


def enable_cpu_loops(environ: MutableMapping[str, str] | None = None) -> CpuLoops:
    """Compile XLA's CPU while loops (every filter's scan) as one kernel each, in this process
    and the subprocesses it starts: sets ``OPTION`` in ``environ["XLA_FLAGS"]`` (default
    ``os.environ``). Call it before the process's first JAX computation (XLA reads its flags
    once, then); ``cpu_loops()`` tells whether it took effect. ``KCKF_XLA_LOOPS=0`` in
    ``environ`` leaves XLA's default alone, ``KCKF_XLA_LOOPS=<bytes>`` sets that bound, and an
    ``XLA_FLAGS`` that names the option already is kept. Returns what it did.

    Example:
        >>> import kckf_jax as kk
        >>> kk.enable_cpu_loops({"XLA_FLAGS": ""}).state
        'on'
    """
    global _STATE
    mine = environ is None
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    have = preset_bytes(flags)
    asked = environ.get(ENV, "").strip()
    if asked and not asked.isdigit():
        raise ValueError(f"{ENV}={asked!r}: expected 0 (XLA's default) or a bound in bytes per "
                         f"loop iteration (kckf-jax's default is {LOOP_BYTES})")
    if asked == "0":
        state = CpuLoops("off", have or XLA_DEFAULT_BYTES,
                         f"{ENV}=0: XLA's default loops")
    elif have is not None:
        state = CpuLoops("preset", have, f"XLA_FLAGS sets {OPTION}={have}; kept")
    else:
        loop_bytes = int(asked) if asked else LOOP_BYTES
        bound = with_option(flags, loop_bytes)
        environ["XLA_FLAGS"] = without_ynn(bound, jaxlib_version())
        ynn = (f", and {YNN_FLAG}={YNN_VALUE} (no library reduction keeps a loop from it)"
               if environ["XLA_FLAGS"] != bound else "")
        state = CpuLoops("on", loop_bytes, f"{OPTION}={loop_bytes} set in XLA_FLAGS{ynn}: "
                                           "XLA compiles each while loop as one kernel")
    if mine:
        _STATE = state
        _probe.cache_clear()
    return state


@functools.lru_cache(maxsize=1)
def _probe() -> bool:
    """Whether XLA compiles a filter-sized loop as one kernel here: a step on lanes (21 x 21
    covariance entries of 64 trials) with a reduction of a product that XLA hands to YNNPACK
    unless told not to (as the exact-rotation KCKF's reverse pass has); the compiled
    program's loop is a call XLA marks as hoisted."""
    import jax
    import jax.numpy as jnp

    def body(c, r):
        P = jnp.tanh(c * 0.5 + r)
        E = jnp.sum(P[:9, None] * P[None], axis=2)
        return P + 0.01 * jnp.sum(E, axis=0)[None], c

    cpu = jax.devices("cpu")[0]
    x = jax.device_put(jnp.zeros((4, 21, 21, 64), jnp.float32), cpu)
    text = jax.jit(lambda x: jax.lax.scan(body, x[0], x)[1]).lower(x).compile().as_text()
    return 'xla_cpu_small_call="true"' in text


def cpu_loops() -> CpuLoops:
    """How XLA compiles while loops (every filter's scan) on the CPU in this process: what
    ``enable_cpu_loops`` did, and whether loops are compiled as one kernel (``one_kernel``,
    measured once: it starts JAX's backend). See the module docstring and
    docs/performance.md.

    Example:
        >>> import kckf_jax as kk
        >>> kk.cpu_loops().state in ("on", "preset", "off", "default", "late")
        True
    """
    one = _probe()
    state = _STATE
    if state.state == "on" and not one:
        return CpuLoops("late", XLA_DEFAULT_BYTES,
                        "enable_cpu_loops() ran after JAX's backend had started, so XLA never "
                        "read the setting: call it before the process's first JAX computation, "
                        f"or set XLA_FLAGS='{with_option('', LOOP_BYTES)}' before starting "
                        "Python", one)
    return state._replace(one_kernel=one)
