"""What a robot is: its leg models (:mod:`.legs`: the :class:`~.legs.LegModel` protocol and the
one registry of leg kinds, :data:`~.legs.LEG_KINDS`)."""
