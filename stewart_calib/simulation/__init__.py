"""The laboratory: true robot, load model, in-situ tracker, trajectories and the closed loop."""
