"""XLA's persistent compilation cache for the ``kckf`` command (the edge: the library itself
never writes to the user's home)."""

from __future__ import annotations

import os


def keep_compiled_programs() -> None:
    """Keep compiled programs between runs of the command (XLA's persistent cache): a second
    ``kckf evaluate`` of the same shapes loads what the first compiled instead of compiling
    again. In ``$KCKF_CACHE_DIR`` (default ``~/.cache/kckf-jax/xla``; empty: off); a cache
    that JAX was given already (``JAX_COMPILATION_CACHE_DIR``) is left as it is."""
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
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
