"""The robot description and its symbolic PCC model (kinematics, Jacobians, export). Above: core."""
