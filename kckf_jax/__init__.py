"""kckf-jax: the Kinematically Constrained Kalman Filter for wearable serial-link robots.

The public API (everything else lives in private modules; docs/architecture.md maps them):

* layout and parameters: ``Robot``, ``Params`` (learnable), ``SensorLimits`` (the physical
  range of the readings), ``ParamsFileError``, ``load_params``, ``save_params``,
  ``params_to_dict``; ``SensorEffects`` (learned sensor effects beyond the paper's models,
  each off unless named in ``EFFECTS``: a clock offset, gyro scales, the joints' play, Hall
  curves beyond Eq. 1; ``Params.with_effects``);
* the filters as model objects (every ``method`` argument takes the object or its name):
  ``AbstractModel``, ``KCKF``, ``KF``, ``ExactKCKF``, ``Gyro``, ``HallL``, ``HallR``;
  ``MODELS`` (the one table of names), ``model_of``, ``register_model``;
* the filter's kernel: ``SensorSeries`` (the readings as recorded), ``FilterState``,
  ``Estimate``, ``METHODS``, ``init_state``, ``step``, ``scan_filter``, ``pad_series``;
  the readings prepared once: ``prepare`` (a recording or a batch) and ``prepare_row`` (a
  lone row) make the ``FilterInput`` that ``step``, ``scan_filter`` and every path compute
  on; ``ScreenedSeries`` (judged, the sensor effects still in; ``screened``'s result).
  The state's block layout and the paper's matrices are internals
  (``kckf_jax._models._blocks``, which benchmarks and tests read);
* running it: ``run_filter`` (one recording), ``filter_batch`` (padded trials),
  ``filter_sessions`` (recorded sessions), ``session_series``, ``session_params``,
  ``screened`` (the readings as the filter uses them, and why not: once for many runs),
  ``GapPolicy`` (what happens across a gap in the rows), ``choose_path`` and ``PathChoice``
  (which path runs, and why), ``PathRun`` (what a path computed), ``PathCost`` (what it
  costs, estimated), ``SmootherLayout`` (how the smoother lays out a batch for a path);
* offline analysis: ``smooth``, ``smooth_batch`` (the fixed-interval RTS smoother; its steady
  layout ``SteadySmoother``), ``hall_nll`` (the Hall readings' negative log-likelihood),
  ``consistency_figures`` (NIS and NEES against a consistent filter's interval),
  ``diagnostics`` (where the error comes from: the innovations' whiteness and the error
  against motion capture decomposed; a ``Diagnostics`` of ``Whiteness`` per channel and
  ``ErrorParts`` per angle);
* the paths (how the same estimates are computed): ``AbstractPath``, ``Sequential``,
  ``Steady``, ``Lanes``, ``Segments``, ``Parallel``, ``Auto``;
* the Hall model (Eq. 1; coefficients in rad): ``hall_angle``, ``hall_slope``,
  ``hall_voltage``;
* sessions: ``Session``, ``SessionError``, ``SessionWarning``, ``read_session``, ``write_session``,
  ``align_mocap``, ``simulate``, ``SimConfig``, ``KINDS``, ``sample_data_dir`` (the sample
  sessions shipped with the package), ``Fault`` and ``inject_faults`` (sensor faults written
  into a session on request);
* set-up mistakes named before filtering (swapped Hall columns, a gyro of the wrong sign, a
  Hall curve that cannot be the sensor's): ``setup_check``, ``SetupFinding``;
* evaluation and fitting: ``rmse_table``, ``fused_hall_error``, ``fit``, ``FitConfig``,
  ``FitResult``, ``FitInterrupted``, ``initial_params``, ``loss_fn``, ``make_batch`` (and its
  ``Batch``), ``shard_batch``; ``estimate_mounting`` (each gyro board's rotation on its link
  from the gyros alone, a fit's start for ``gyro_mounting``);
* live filtering and deployment: ``StreamingFilter``, ``PacketParser``, ``Packet``,
  ``STATUSES``, ``low_latency``, ``export_step``; where packets come from and go (``Source``,
  which hands over packets, ``Oversized`` ones, ``Foreign`` ones from another sender and the
  ``Handover`` of a robot back on a new address; ``open_source``, ``open_sink``,
  ``run_stream``; the Lab Streaming Layer's ``LslSource`` and ``LslSink``, and
  ``lsl_loopback_config`` to keep LSL on this machine);
* faulty readings (what the step does not use, and why): ``FAULT_KINDS``,
  ``fault_stretches`` (``Estimate.faults`` by column, kind and time); ``FaultPolicy`` (what
  the health monitor's findings do: ``isolate``, ``report`` or ``off``; ``FAULT_POLICIES``,
  ``Params.with_faults``) and ``model_mismatch`` (the paper's gyro pairs that the data show
  do not read the same rate, following the pose: the linear model's limit, not a fault);
  ``hall_drift`` (a Hall sensor drifting slowly from its partner, which the monitor's fast
  rules do not see); ``bias_steps`` (a gyro whose bias stepped, from a ``kckf3d`` estimate's
  biases: that model has no gyro pairs for the monitor to compare);
* analysis: ``observability_ranks``;
* the one process-wide setting it offers, made only when asked (XLA's CPU while loops
  compiled as one kernel each; importing kckf_jax changes nothing in the process):
  ``enable_cpu_loops``, and ``cpu_loops`` (what it did, measured; a ``CpuLoops``).

The other papers' systems are in ``kckf_jax.filters``.
"""

from ._analysis._diagnostics import Diagnostics as Diagnostics
from ._analysis._diagnostics import ErrorParts as ErrorParts
from ._analysis._diagnostics import Whiteness as Whiteness
from ._analysis._diagnostics import consistency_figures as consistency_figures
from ._analysis._diagnostics import diagnostics as diagnostics
from ._analysis._metrics import fused_hall_error as fused_hall_error
from ._analysis._metrics import rmse_table as rmse_table
from ._analysis._observability import observability_ranks as observability_ranks
from ._fitting._fit import Batch as Batch
from ._fitting._fit import FitConfig as FitConfig
from ._fitting._fit import fit as fit
from ._fitting._fit import initial_params as initial_params
from ._fitting._fit import loss_fn as loss_fn
from ._fitting._fit import make_batch as make_batch
from ._fitting._fit import package_version as _package_version
from ._fitting._fit import shard_batch as shard_batch
from ._fitting._mounting import estimate_mounting as estimate_mounting
from ._fitting._train import FitInterrupted as FitInterrupted
from ._fitting._train import FitResult as FitResult
from ._models._classes import KCKF as KCKF
from ._models._classes import KF as KF
from ._models._classes import METHODS as METHODS
from ._models._classes import MODELS as MODELS
from ._models._classes import AbstractModel as AbstractModel
from ._models._classes import ExactKCKF as ExactKCKF
from ._models._classes import Gyro as Gyro
from ._models._classes import HallL as HallL
from ._models._classes import HallR as HallR
from ._models._classes import init_state as init_state
from ._models._classes import model_of as model_of
from ._models._classes import register_model as register_model
from ._models._classes import scan_filter as scan_filter
from ._models._classes import step as step
from ._models._effects import EFFECTS as EFFECTS
from ._models._effects import SensorEffects as SensorEffects
from ._models._fault_policy import FAULT_POLICIES as FAULT_POLICIES
from ._models._fault_policy import FaultPolicy as FaultPolicy
from ._models._hall import hall_angle as hall_angle
from ._models._hall import hall_slope as hall_slope
from ._models._hall import hall_voltage as hall_voltage
from ._models._kernel import Estimate as Estimate
from ._models._kernel import FilterInput as FilterInput
from ._models._kernel import FilterState as FilterState
from ._models._kernel import SensorSeries as SensorSeries
from ._models._limits import SensorLimits as SensorLimits
from ._models._params import Params as Params
from ._models._params import ParamsFileError as ParamsFileError
from ._models._params import load_params as load_params
from ._models._params import params_to_dict as params_to_dict
from ._models._params import save_params as save_params
from ._models._robot import Robot as Robot
from ._paths import AbstractPath as AbstractPath
from ._paths import Auto as Auto
from ._paths import Lanes as Lanes
from ._paths import Parallel as Parallel
from ._paths import PathChoice as PathChoice
from ._paths import PathCost as PathCost
from ._paths import PathRun as PathRun
from ._paths import Segments as Segments
from ._paths import Sequential as Sequential
from ._paths import SmootherLayout as SmootherLayout
from ._paths import Steady as Steady
from ._paths._cpu_loops import CpuLoops as CpuLoops
from ._paths._cpu_loops import cpu_loops as cpu_loops
from ._paths._cpu_loops import enable_cpu_loops as enable_cpu_loops
from ._paths._likelihood import hall_nll as hall_nll
from ._paths._run import choose_path as choose_path
from ._paths._run import filter_batch as filter_batch
from ._paths._run import filter_sessions as filter_sessions
from ._paths._run import run_filter as run_filter
from ._paths._run import screened as screened
from ._paths._run import session_params as session_params
from ._paths._run import session_series as session_series
from ._paths._smooth import smooth as smooth
from ._paths._smooth import smooth_batch as smooth_batch
from ._paths._steady_smooth import SteadySmoother as SteadySmoother
from ._readings._batching import pad_series as pad_series
from ._readings._bias_steps import bias_steps as bias_steps
from ._readings._drift import hall_drift as hall_drift
from ._readings._gaps import GapPolicy as GapPolicy
from ._readings._mismatch import model_mismatch as model_mismatch
from ._readings._prepare import ScreenedSeries as ScreenedSeries
from ._readings._prepare import prepare as prepare
from ._readings._prepare import prepare_row as prepare_row
from ._readings._screen import FAULT_KINDS as FAULT_KINDS
from ._readings._screen import fault_stretches as fault_stretches
from ._readings._setup_check import SetupFinding as SetupFinding
from ._readings._setup_check import setup_check as setup_check
from ._sessions._containers import sample_data_dir as sample_data_dir
from ._sessions._session import Session as Session
from ._sessions._session import SessionError as SessionError
from ._sessions._session import SessionWarning as SessionWarning
from ._sessions._session import align_mocap as align_mocap
from ._sessions._session import read_session as read_session
from ._sessions._session import write_session as write_session
from ._sessions._sim_faults import Fault as Fault
from ._sessions._sim_faults import inject_faults as inject_faults
from ._sessions._simulate import KINDS as KINDS
from ._sessions._simulate import SimConfig as SimConfig
from ._sessions._simulate import simulate as simulate
from ._stream import STATUSES as STATUSES
from ._stream import Foreign as Foreign
from ._stream import Handover as Handover
from ._stream import LslSink as LslSink
from ._stream import LslSource as LslSource
from ._stream import Oversized as Oversized
from ._stream import Packet as Packet
from ._stream import PacketParser as PacketParser
from ._stream import Source as Source
from ._stream import StreamingFilter as StreamingFilter
from ._stream import low_latency as low_latency
from ._stream import lsl_loopback_config as lsl_loopback_config
from ._stream import open_sink as open_sink
from ._stream import open_source as open_source
from ._stream import run_stream as run_stream
from ._stream._export import export_step as export_step

__version__ = _package_version()
