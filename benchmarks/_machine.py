"""A description of the machine a benchmark ran on (recorded beside every figure)."""

from __future__ import annotations

import os
import platform


def machine() -> dict:
    import jax

    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    devices = jax.devices()
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in devices],
        "device_kind": devices[0].device_kind,
    }


def require_peers(script: str, modules: tuple[str, ...] = ("dynamax", "filterpy")) -> None:
    """Exit at once, saying what to install, when a peer library this benchmark compares with
    is missing (they are the ``bench`` extra, not the package's dependencies)."""
    import importlib.util
    import sys

    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        sys.exit(f"{script} compares with {', '.join(modules)}; missing: {', '.join(missing)}. "
                 "Install them with pip install '.[bench]' (from the repository), or run "
                 "with --no-peers for kckf-jax alone")
