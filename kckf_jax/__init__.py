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
from ._metrics import rmse_table as rmse_table
from ._model import paper_matrices as paper_matrices
from ._model import structure as structure
from ._observability import observability_ranks as observability_ranks
from ._params import Params as Params
from ._robot import Robot as Robot
from ._run import (
    filter_sessions as filter_sessions,
)
from ._run import (
    session_params as session_params,
)
from ._run import (
    session_series as session_series,
)
from ._session import (
    Session as Session,
)
from ._session import (
    SessionError as SessionError,
)
from ._session import (
    align_mocap as align_mocap,
)
from ._session import (
    read_session as read_session,
)
from ._session import (
    write_session as write_session,
)
from ._simulate import KINDS as KINDS
from ._simulate import SimConfig as SimConfig
from ._simulate import simulate as simulate

__version__ = "0.1.0"
