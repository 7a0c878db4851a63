"""rerun recordings: the platform in 3D, parameters vs truth, pose errors, trajectories."""
