"""The models: the robot's layout, Eq. 1, the parameters and sensor effects, the state's blocks,
the model classes, the exact rotations and the kernel's step."""
