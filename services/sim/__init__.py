"""Simulated fleets: procedural worlds with exact ground truth, range sensors, robot paths and odometry."""
