"""Sources of observational trajectories (synthetic world, MIMIC-III)."""
