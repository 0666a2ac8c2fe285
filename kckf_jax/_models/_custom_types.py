"""The one vocabulary of array dimensions, and the array types built from it.

Every shape annotation of the package uses these names (jaxtyping binds a name to one size
within a call, so a mismatch between two arguments is caught when tests run with runtime
checking):

========  ==========================================================================
``B``     trials of a batch
``T``     time steps (rows) of a recording
``G``     gyro channels, ``3 (n + 1)``; ``Gu`` the ones the filters read
``M``     Hall sensors, ``2 J``
``J``     joint axes; ``K = J + Nt`` estimated angles (joint axes, then torso axes)
``Nb``    axis blocks of the filter (one per torso axis, ``_model.Structure``)
``Nz``    a block's state in the filter's coordinates; ``Ny = Nz + n_e`` with the
          constraint coordinate; ``m`` joints per block, ``m1 = m + 1`` rates per block
``Np``    the side of a stored covariance (``Nz`` for the Kalman filters, 0 for baselines)
``Nq``    a batch row's flattened block state, ``Nb Nz``
``R``     rows handled together (a head, a chunk, a block of rows)
``C``     chunks of rows; ``I`` readings per row (``Gu + M``); ``O`` outputs of a chunk
          (``L 2K`` for chunks of ``L`` rows); ``Y`` a chunk's readings (``L I``) and
          ``X`` those and an entering state (``L I + Nq``)
========  ==========================================================================
"""

from __future__ import annotations

from jaxtyping import Array, Bool, Float

#: One block's state and covariance, any leading batch axes.
BlockState = Float[Array, "*B Nb Nz"]
BlockCov = Float[Array, "*B Nb Nz Nz"]
#: Per-row affine maps of the mean, ``z_k = A_k z_{k-1} + Gr_k r_k + Gh_k h_k`` (one block
#: each).
BlockMap = Float[Array, "*R Nb Nz Nz"]
RateMap = Float[Array, "*R Nb Nz m1"]
HallMap = Float[Array, "*R Nb Nz m"]
#: A row's per-block inputs: rates (rad/s), process noise terms, fused Hall readings (rad),
#: their variances (rad^2) and whether they exist.
BlockRates = Float[Array, "*R Nb m1"]
BlockHall = Float[Array, "*R Nb m"]
BlockValid = Bool[Array, "*R Nb m"]
Scalar = Float[Array, ""]

__all__ = ["BlockCov", "BlockHall", "BlockMap", "BlockRates", "BlockState", "BlockValid",
           "HallMap", "RateMap", "Scalar"]
