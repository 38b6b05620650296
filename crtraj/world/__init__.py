"""Scenes: obstacles over time, their packing for solvers, the safety margin, live obstacle sources. Above: model."""
