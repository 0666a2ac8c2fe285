"""The other papers' systems, one package each, on the package's step/scan/vmap pattern and
its Kalman helpers (``kckf_jax._models._kalman``), fitted by its one training loop
(docs/other_filters.md):

* ``arm_imu``: the arm exoskeleton + IMU fusion filter of Chen, Yang and Hofschulte, its
  simulator (exoskeleton, Xsens MTi, optical tracking) and experiment;
* ``markov``: the Markovian (MJLS) filter of a lower-limb exoskeleton and its per-segment KF,
  the gait simulator and the experiments (Fig. 9, fitting Table 2).

No filter imports a simulator; simulators and experiments import their filter.
"""

from .arm_imu import ArmImuEstimate as ArmImuEstimate
from .arm_imu import ArmImuParams as ArmImuParams
from .arm_imu import ArmImuSeries as ArmImuSeries
from .arm_imu import ArmImuState as ArmImuState
from .arm_imu import ArmSimConfig as ArmSimConfig
from .arm_imu import ArmTrial as ArmTrial
from .arm_imu import arm_imu_batch as arm_imu_batch
from .arm_imu import arm_imu_experiment as arm_imu_experiment
from .arm_imu import arm_imu_init as arm_imu_init
from .arm_imu import arm_imu_series as arm_imu_series
from .arm_imu import arm_imu_step as arm_imu_step
from .arm_imu import draw_exoskeleton as draw_exoskeleton
from .arm_imu import first_valid_rotation as first_valid_rotation
from .arm_imu import pad_arm_imu as pad_arm_imu
from .arm_imu import remove_gyro_bias as remove_gyro_bias
from .arm_imu import run_arm_imu as run_arm_imu
from .arm_imu import scan_arm_imu as scan_arm_imu
from .arm_imu import simulate_arm_trial as simulate_arm_trial
from .markov import GaitConfig as GaitConfig
from .markov import GaitSeries as GaitSeries
from .markov import GaitTrials as GaitTrials
from .markov import MarkovEstimate as MarkovEstimate
from .markov import MarkovParams as MarkovParams
from .markov import MarkovState as MarkovState
from .markov import fit_markov as fit_markov
from .markov import gait_series as gait_series
from .markov import gated_accel_error as gated_accel_error
from .markov import markov_batch as markov_batch
from .markov import markov_experiment as markov_experiment
from .markov import markov_init as markov_init
from .markov import markov_loss as markov_loss
from .markov import markov_step as markov_step
from .markov import matched_markov_params as matched_markov_params
from .markov import perturb_markov_params as perturb_markov_params
from .markov import run_markov as run_markov
from .markov import scan_markov as scan_markov
from .markov import simulate_gait as simulate_gait
from .markov import to_paper as to_paper
