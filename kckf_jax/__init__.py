"""kckf-jax: the Kinematically Constrained Kalman Filter for wearable serial-link robots."""

from ._filter import (
    METHODS as METHODS,
)
from ._filter import (
    Estimate as Estimate,
)
from ._filter import (
    FilterState as FilterState,
)
from ._filter import (
    SensorSeries as SensorSeries,
)
from ._filter import (
    filter_batch as filter_batch,
)
from ._filter import (
    init_state as init_state,
)
from ._filter import (
    pad_series as pad_series,
)
from ._filter import (
    run_filter as run_filter,
)
from ._filter import (
    step as step,
)
from ._hall import hall_angle as hall_angle
from ._hall import hall_slope as hall_slope
from ._hall import hall_voltage as hall_voltage
from ._model import paper_matrices as paper_matrices
from ._params import Params as Params
from ._robot import Robot as Robot

__version__ = "0.1.0"
