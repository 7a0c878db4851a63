"""What a robot *is*: its platform geometry, leg models, kinematics, statics, drive and unknowns.

:mod:`.legs` holds the leg-model protocol (:class:`~.legs.LegModel`, spec §15) and
:data:`~.legs.LEG_KINDS`, the one registry of leg kinds. Each leg kind is one module here (the
prismatic :class:`~stewart_calib.model.platform.LegGeometry` in ``platform.py``) that implements it: its
parameter vector M and names, the closure residual of each leg in one coordinate e_i, its
Jacobians, and its inverse and forward kinematics. :class:`RotaryLegs` is the servo-horn (6-RSS)
leg set of spec §15.
"""

from .rotary import RotaryLegs

__all__ = ["RotaryLegs"]
