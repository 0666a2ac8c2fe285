"""Further filters on the package's step/scan pattern (see docs/other_filters.md).

* ``arm_imu``: the arm exoskeleton + IMU fusion filter of Chen, Yang and Hofschulte;
  ``arm_sim``: its simulator (exoskeleton, Xsens MTi, optical tracking) and experiment.
"""

from .arm_imu import ArmImuEstimate as ArmImuEstimate
from .arm_imu import ArmImuParams as ArmImuParams
from .arm_imu import ArmImuSeries as ArmImuSeries
from .arm_imu import ArmImuState as ArmImuState
from .arm_imu import arm_imu_batch as arm_imu_batch
from .arm_imu import arm_imu_init as arm_imu_init
from .arm_imu import arm_imu_series as arm_imu_series
from .arm_imu import arm_imu_step as arm_imu_step
from .arm_imu import first_valid_rotation as first_valid_rotation
from .arm_imu import pad_arm_imu as pad_arm_imu
from .arm_imu import run_arm_imu as run_arm_imu
from .arm_imu import scan_arm_imu as scan_arm_imu
from .arm_sim import ArmSimConfig as ArmSimConfig
from .arm_sim import ArmTrial as ArmTrial
from .arm_sim import arm_imu_experiment as arm_imu_experiment
from .arm_sim import draw_exoskeleton as draw_exoskeleton
from .arm_sim import remove_gyro_bias as remove_gyro_bias
from .arm_sim import simulate_arm_trial as simulate_arm_trial
