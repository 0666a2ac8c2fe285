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
(``cpu_loops()`` measures it), and the call changes nothing there.

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
        environ["XLA_FLAGS"] = with_option(flags, loop_bytes)
        state = CpuLoops("on", loop_bytes, f"{OPTION}={loop_bytes} set in XLA_FLAGS: XLA "
                                           "compiles each while loop as one kernel")
    if mine:
        _STATE = state
        _probe.cache_clear()
    return state


@functools.lru_cache(maxsize=1)
def _probe() -> bool:
    """Whether XLA compiles a loop touching 2 KiB per iteration (a filter step on lanes is
    larger) as one kernel here: the compiled program's loop is a call XLA marks as hoisted."""
    import jax
    import jax.numpy as jnp

    def body(c, r):
        return jnp.tanh(c * 0.5 + r), c

    cpu = jax.devices("cpu")[0]
    x = jax.device_put(jnp.zeros((4, 64, 8), jnp.float32), cpu)
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
