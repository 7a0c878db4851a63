"""GTSAM custom factors: one module per factor type, each a pure residual with analytic
Jacobians plus a thin ``gtsam.CustomFactor`` adapter."""
