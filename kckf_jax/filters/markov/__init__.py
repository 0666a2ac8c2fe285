"""The Markovian (MJLS) Kalman filter of a lower-limb exoskeleton and its per-segment baseline:
the filter and its parameters (``_filter.py``), the gait simulator (``_sim.py``) and the
experiments (``_experiment.py``: the paper's Fig. 9, the gradient fit of Table 2)."""

from ._experiment import MarkovLoss as MarkovLoss
from ._experiment import fit_markov as fit_markov
from ._experiment import markov_experiment as markov_experiment
from ._experiment import uncertainty_factors as uncertainty_factors
from ._filter import GaitSeries as GaitSeries
from ._filter import MarkovEstimate as MarkovEstimate
from ._filter import MarkovParams as MarkovParams
from ._filter import MarkovState as MarkovState
from ._filter import accel_angle as accel_angle
from ._filter import markov_batch as markov_batch
from ._filter import markov_init as markov_init
from ._filter import markov_loss as markov_loss
from ._filter import markov_step as markov_step
from ._filter import mean_error_deg as mean_error_deg
from ._filter import perturb_markov_params as perturb_markov_params
from ._filter import reliability as reliability
from ._filter import run_markov as run_markov
from ._filter import scan_markov as scan_markov
from ._filter import to_paper as to_paper
from ._sim import GaitConfig as GaitConfig
from ._sim import GaitTrials as GaitTrials
from ._sim import gait_series as gait_series
from ._sim import gated_accel_error as gated_accel_error
from ._sim import matched_markov_params as matched_markov_params
from ._sim import simulate_gait as simulate_gait
