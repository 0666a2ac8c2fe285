"""Ways of computing the filter's estimates, as strategy objects (one module each).

* ``AbstractPath`` (``_base.py``), with the one regularity check (``regular_step``) and the
  one convergence measure (``relative_change``) every path and the streaming filter use;
* ``Sequential``: the scan of the kernel's ``step`` (the reference, computes anything);
* ``Steady``: the converged filter's constant map (regular recordings), built from the affine
  maps of a step (``_affine.py``), a scan of per-row maps (``_row_scan.py``) and chunks of
  matrix products (``_chunks.py``), each reverse mode beside its forward;
* ``Lanes``: the kernel's arithmetic with the trials as lanes (batches of recorded data:
  irregular time steps, missing readings, the voltage noise model);
* ``Segments``: one long recording cut into warmed-up, checked segments run as lanes (recorded
  data, one recording or a few);
* ``Parallel``: covariance phase, then the mean by associative scan (accelerators);
* ``Auto``: the policy.

To add a path: a final ``AbstractPath`` subclass (``applies`` and ``run``; the other questions
have defaults) passed as ``path=`` to any filter call or loss, or offered to the policy as
``Auto(before=(MyPath(),))``; nothing else changes (``tests/test_paths.py`` adds one so). A
path of the package also gets a module of its own here, an export, and a name in ``PATHS``.
"""

from ._affine import converged_map as converged_map
from ._auto import Auto as Auto
from ._base import STEP_TOL_S as STEP_TOL_S
from ._base import AbstractPath as AbstractPath
from ._base import PathChoice as PathChoice
from ._base import PathCost as PathCost
from ._base import PathRun as PathRun
from ._base import SmootherLayout as SmootherLayout
from ._base import is_traced as is_traced
from ._base import readings_present as readings_present
from ._base import regular_step as regular_step
from ._base import relative_change as relative_change
from ._lanes import Lanes as Lanes
from ._parallel import Parallel as Parallel
from ._segments import Segments as Segments
from ._sequential import Sequential as Sequential
from ._steady import Steady as Steady

PATHS = {"auto": Auto, "sequential": Sequential, "steady": Steady, "lanes": Lanes,
         "segments": Segments, "parallel": Parallel}


def as_path(path: str | AbstractPath) -> AbstractPath:
    """A path object from a name (``"auto"``, ``"sequential"``, ``"steady"``, ``"lanes"``,
    ``"segments"``, ``"parallel"``) or a path object itself."""
    if isinstance(path, AbstractPath):
        return path
    if path not in PATHS:
        raise ValueError(f"path must be one of {', '.join(PATHS)} or a path object, got "
                         f"{path!r}")
    return PATHS[path]()
