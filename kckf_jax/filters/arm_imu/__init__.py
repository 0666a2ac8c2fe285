"""The arm exoskeleton + IMU fusion filter of Chen, Yang and Hofschulte: the filter
(``_filter.py``), its simulator (``_sim.py``) and its experiment (``_experiment.py``)."""

from ._experiment import arm_imu_experiment as arm_imu_experiment
from ._filter import ArmImuEstimate as ArmImuEstimate
from ._filter import ArmImuParams as ArmImuParams
from ._filter import ArmImuSeries as ArmImuSeries
from ._filter import ArmImuState as ArmImuState
from ._filter import arm_imu_batch as arm_imu_batch
from ._filter import arm_imu_init as arm_imu_init
from ._filter import arm_imu_series as arm_imu_series
from ._filter import arm_imu_step as arm_imu_step
from ._filter import first_valid_rotation as first_valid_rotation
from ._filter import pad_arm_imu as pad_arm_imu
from ._filter import run_arm_imu as run_arm_imu
from ._filter import scan_arm_imu as scan_arm_imu
from ._sim import ArmSimConfig as ArmSimConfig
from ._sim import ArmTrial as ArmTrial
from ._sim import draw_exoskeleton as draw_exoskeleton
from ._sim import remove_gyro_bias as remove_gyro_bias
from ._sim import simulate_arm_trial as simulate_arm_trial
