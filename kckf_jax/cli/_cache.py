"""XLA's persistent compilation cache for the ``kckf`` command (the edge: the library itself
never writes to the user's home)."""

from __future__ import annotations

import os


def keep_compiled_programs() -> None:
    """Keep compiled programs between runs of the command (XLA's persistent cache): a second
    ``kckf evaluate`` of the same shapes loads what the first compiled instead of compiling
    again. In ``$KCKF_CACHE_DIR`` (default ``~/.cache/kckf-jax/xla``; empty: off), programs
    that took ``min_compile_s()`` or longer to compile; a cache that JAX was given already
    (``JAX_COMPILATION_CACHE_DIR``) is left as it is."""
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    path = os.environ.get("KCKF_CACHE_DIR",
                          os.path.join(os.path.expanduser("~"), ".cache", "kckf-jax", "xla"))
    if not path:
        return
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return  # a read-only home: compile every time
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s())


def min_compile_s() -> float:
    """Programs that compiled faster than this are not kept: ``$KCKF_CACHE_MIN_COMPILE_S``
    seconds, default 0.1 (the hour's filter, 0.53 s to compile, loads in 0.03-0.06 s; the
    regularity check, 0.17 s, is worth keeping; below 0.1 s loading costs about what
    compiling does)."""
    raw = os.environ.get("KCKF_CACHE_MIN_COMPILE_S", "0.1").strip()
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not value >= 0.0:
        raise ValueError(f"KCKF_CACHE_MIN_COMPILE_S={raw!r}: expected seconds, 0 or more")
    return value
