"""Actuators, limits, set-points, admission, the streamer, transports, protocol, simulated devices. Above: control."""
