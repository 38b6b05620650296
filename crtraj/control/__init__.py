"""The receding-horizon replanner, tracking, and the closed loop with its ports. Above: planning."""
