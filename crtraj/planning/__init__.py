"""Planners, their query/result/stop types, state and motion validity, steer and safe IK. Above: world."""
