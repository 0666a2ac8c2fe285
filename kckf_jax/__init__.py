"""kckf-jax: the Kinematically Constrained Kalman Filter for wearable serial-link robots.

The public API (everything else lives in private modules):

* layout and parameters: ``Robot``, ``Params`` (learnable), ``load_params``, ``save_params``;
* filters: ``step``, ``init_state``, ``run_filter`` (jitted ``lax.scan``), ``filter_batch``
  (``vmap``), ``METHODS``;
* sessions: ``read_session``, ``write_session``, ``Session``, ``simulate``;
* evaluation and fitting: ``filter_sessions``, ``rmse_table``, ``fit``, ``FitConfig``;
* analysis: ``observability_ranks``, ``paper_matrices``.
"""

from ._filter import METHODS as METHODS
from ._filter import Estimate as Estimate
from ._filter import FilterState as FilterState
from ._filter import SensorSeries as SensorSeries
from ._filter import filter_batch as filter_batch
from ._filter import init_state as init_state
from ._filter import pad_series as pad_series
from ._filter import run_filter as run_filter
from ._filter import scan_filter as scan_filter
from ._filter import step as step
from ._fit import FitConfig as FitConfig
from ._fit import FitInterrupted as FitInterrupted
from ._fit import FitResult as FitResult
from ._fit import fit as fit
from ._fit import loss_fn as loss_fn
from ._fit import make_batch as make_batch
from ._fit import shard_batch as shard_batch
from ._hall import hall_angle as hall_angle
from ._hall import hall_slope as hall_slope
from ._hall import hall_voltage as hall_voltage
from ._metrics import fused_hall_error as fused_hall_error
from ._metrics import rmse_table as rmse_table
from ._model import full_state as full_state
from ._model import paper_matrices as paper_matrices
from ._model import structure as structure
from ._observability import observability_ranks as observability_ranks
from ._params import Params as Params
from ._params import ParamsFileError as ParamsFileError
from ._params import load_params as load_params
from ._params import params_to_dict as params_to_dict
from ._params import save_params as save_params
from ._robot import Robot as Robot
from ._run import filter_sessions as filter_sessions
from ._run import session_params as session_params
from ._run import session_series as session_series
from ._session import Session as Session
from ._session import SessionError as SessionError
from ._session import align_mocap as align_mocap
from ._session import read_session as read_session
from ._session import write_session as write_session
from ._simulate import KINDS as KINDS
from ._simulate import SimConfig as SimConfig
from ._simulate import simulate as simulate

__version__ = "0.1.0"
