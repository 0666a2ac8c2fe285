"""XLA's CPU while loops compiled as one kernel each: the one process-wide setting kckf-jax
makes, when it is imported.

Every filter here is a ``lax.scan``, an XLA while loop. Since jax 0.4.32 XLA's CPU runtime runs
each iteration of a loop as a sequence of "thunks", one per fused kernel, through a dataflow
executor: a filter step on lanes is 50 to 60 kernels of a few hundred numbers each, and
launching them, not their arithmetic, was most of the step's time. XLA has a pass that
compiles a whole while loop into one function, as the runtime before 0.4.32 did for every
loop (``SmallWhileLoopHoistingPass``): it takes a loop with no dot, convolution, scatter,
custom call or collective whose one iteration touches fewer than
``xla_cpu_small_while_loop_byte_threshold`` bytes, 1,024 by default, which none of ours does.
kckf-jax raises that bound to ``LOOP_BYTES`` (every loop the pass can take) in ``XLA_FLAGS``
when it is imported, before JAX's backend has started, since XLA reads its flags once, then.
Loops with matrix products (the steady path's chunks) are not taken and run as before.

Measured (AMD EPYC, 2 cores, jax 0.10.2, float32, recorded-like bench rows; both settings
alternating in processes of their own, medians; ``python benchmarks/cpu_loops.py``, figures
in benchmarks/README.md): one fitting step on 64 x 10,000 rows 1.15 -> 0.52 s, the lanes
filter of 1,024 trials x 2,000 rows 2.06 -> 0.84 s, the smoother on one hour 4.2 -> 1.1 s, the
sequential filter on one hour 0.93 -> 0.32 s; the vmapped sequential step of 64 trials, whose
larger kernels no longer share two threads, 1.08x slower (``Auto`` gives 64 trials to the
lanes path).

The setting is the process's: any other JAX program in it compiles its loops this way too, and
subprocesses inherit ``XLA_FLAGS``. ``KCKF_XLA_LOOPS=0`` in the environment leaves XLA's
default alone; ``KCKF_XLA_LOOPS=<bytes>`` sets that bound instead; an ``XLA_FLAGS`` that
already names the option is kept as it is. ``cpu_loops()`` says which of these happened.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Callable, MutableMapping
from typing import NamedTuple

import jax
from jax._src import xla_bridge  # JAX's record of started backends: no public API tells it

#: XLA's option: loops whose one iteration touches fewer bytes are compiled as one kernel.
OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: The bound kckf-jax sets: 1 TiB, every loop the pass can take. Smaller bounds leave the larger
#: batches' loops to the thunk runtime, which was slower there at every size measured
#: (``python benchmarks/cpu_loops.py --cases lanes_1024,lanes_4096 --bounds ...``,
#: benchmarks/README.md).
LOOP_BYTES = 1 << 40
#: The environment variable that overrides it: ``0`` for XLA's default, or a bound in bytes.
ENV = "KCKF_XLA_LOOPS"
#: XLA's own default bound (``cpu_options.cc``), for the report.
XLA_DEFAULT_BYTES = 1024

_EXTRA = "--xla_backend_extra_options="


class CpuLoops(NamedTuple):
    """How XLA compiles while loops on the CPU in this process (``cpu_loops()``).

    Attributes:
        state: ``"on"`` (kckf-jax set the bound when it was imported), ``"preset"``
            (``XLA_FLAGS`` already named the option; kept), ``"off"`` (``KCKF_XLA_LOOPS=0``:
            XLA's default), ``"late"`` (JAX's backend had started before kckf-jax was
            imported, so XLA had read its flags already: XLA's default, unless they named it).
        loop_bytes: the bound in effect, in bytes per loop iteration.
        detail: the same in words, with what to do about it where something can be done.
    """

    state: str
    loop_bytes: int
    detail: str


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


def configure(environ: MutableMapping[str, str] = os.environ,
              started: Callable[[], bool] | None = None) -> CpuLoops:
    """Set ``OPTION`` in ``environ["XLA_FLAGS"]`` unless ``KCKF_XLA_LOOPS=0``, the flags name
    it already, or JAX's backend has started (``started()``; then XLA has read its flags and
    the setting could not take effect: a warning says so when the backend is a CPU)."""
    flags = environ.get("XLA_FLAGS", "")
    have = preset_bytes(flags)
    asked = environ.get(ENV, "").strip()
    if asked and not asked.isdigit():
        raise ValueError(f"{ENV}={asked!r}: expected 0 (XLA's default) or a bound in bytes per "
                         f"loop iteration (kckf-jax's default is {LOOP_BYTES})")
    if asked == "0":
        return CpuLoops("off", have or XLA_DEFAULT_BYTES,
                        f"{ENV}=0: XLA's default, each loop iteration run kernel by kernel")
    if have is not None:
        return CpuLoops("preset", have, f"XLA_FLAGS sets {OPTION}={have}; kept")
    if (started or _backend_started)():
        detail = (f"JAX's backend started before kckf_jax was imported, so XLA had read its "
                  f"flags: each loop iteration runs kernel by kernel, and the filters run 2-4x "
                  f"slower on a CPU. Import kckf_jax before running any JAX computation, or "
                  f"set XLA_FLAGS='{with_option('', LOOP_BYTES)}' before starting Python "
                  f"({ENV}=0 silences this)")
        if _cpu_backend():
            warnings.warn(detail, stacklevel=2)
        return CpuLoops("late", XLA_DEFAULT_BYTES, detail)
    loop_bytes = int(asked) if asked else LOOP_BYTES
    environ["XLA_FLAGS"] = with_option(flags, loop_bytes)
    return CpuLoops("on", loop_bytes, f"kckf_jax set {OPTION}={loop_bytes} in XLA_FLAGS: "
                                      "XLA compiles each while loop as one kernel")


def _backend_started() -> bool:
    return xla_bridge.backends_are_initialized()


def _cpu_backend() -> bool:
    return jax.default_backend() == "cpu"


_STATE = configure()


def cpu_loops() -> CpuLoops:
    """How XLA compiles while loops (every filter's scan) on the CPU in this process: set by
    kckf-jax when it was imported (``"on"``), by ``XLA_FLAGS`` (``"preset"``), left at XLA's
    default (``"off"``, ``"late"``). See the module docstring and docs/performance.md.

    Example:
        >>> import kckf_jax as kk
        >>> kk.cpu_loops().state in ("on", "preset", "off", "late")
        True
    """
    return _STATE
