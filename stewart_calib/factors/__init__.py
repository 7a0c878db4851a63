"""GTSAM custom factors: one module per factor type, each a pure residual with analytic
Jacobians plus a thin ``gtsam.CustomFactor`` adapter.

* :mod:`.drive_leg` — pose ↔ δM, one factor per drive leg (stroke q_i).
* :mod:`.tracker_leg` — pose only, one factor per grating reading (tight coupling).
* :mod:`.tracker_pose` — pose prior from tracker FK (loose coupling, the paper's way).
* :mod:`.random_walk` — δM random walk between parameter windows and the tolerance prior.
"""
