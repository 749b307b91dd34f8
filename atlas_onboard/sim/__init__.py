"""SITL-style simulation: trajectories, rendered cameras, simulated autopilots, scenarios, reports."""
