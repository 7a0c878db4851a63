"""What a robot *is*: its leg models, and in time its platform geometry, kinematics and drive.

Each leg kind is one module here that implements the leg-model protocol (spec §15, issue 42):
its parameter vector M and names, the closure residual of each leg in one coordinate e_i, its
Jacobians, and its inverse and forward kinematics. :class:`RotaryLegs` is the servo-horn (6-RSS)
leg set of spec §15.
"""

from .rotary import RotaryLegs

__all__ = ["RotaryLegs"]
