"""Per-sample working data: what one row of the measurement log holds (spec §3), and the
simulator's truth for a log (spec §4).

Kept apart from the fixed geometry in :mod:`stewart_calib.model.platform`. Code works in mm and
rad; the log's degrees are converted at the file edge (:mod:`stewart_calib.io`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from itertools import repeat

import numpy as np

#: the input channel of the payload [kg], a scalar per sample (spec §3 ``load_kg``, §10)
LOAD_KG = "load_kg"
#: the input channel of each leg's temperature [°C], ``(6,)`` per sample (spec §17 ``temp1_C … temp6_C``
#: or ``temp_C`` for all legs)
TEMPERATURE_C = "temperature_C"
#: the input channel of the direction gravity acts in, a unit vector in {J} ``(3,)`` per sample
#: (spec §17 ``gravity_x gravity_y gravity_z``)
GRAVITY = "gravity"

#: each channel's values per sample: () a scalar, (n,) a vector
CHANNEL_SHAPES: dict[str, tuple[int, ...]] = {LOAD_KG: (), TEMPERATURE_C: (6,), GRAVITY: (3,)}

#: what a sample without a channel takes for it where a log's rows are packed (no payload: 0 kg);
#: NaN for the others
CHANNEL_DEFAULTS: dict[str, float] = {LOAD_KG: 0.0}


def _packed_columns() -> dict[str, slice]:
    """Each channel's columns in a packed row, in :data:`CHANNEL_SHAPES`' order."""
    columns, start = {}, 0
    for name, shape in CHANNEL_SHAPES.items():
        width = int(np.prod(shape, dtype=int))
        columns[name] = slice(start, start + width)
        start += width
    return columns


#: each channel's columns in a row of :func:`packed_inputs`, in :data:`CHANNEL_SHAPES`' order
PACKED_COLUMNS = _packed_columns()
#: entries of :func:`packed_inputs`
PACKED_WIDTH = sum(columns.stop - columns.start for columns in PACKED_COLUMNS.values())
#: the row of :func:`packed_inputs` of a sample without channels: :data:`CHANNEL_DEFAULTS`, else NaN
PACKED_DEFAULTS = np.concatenate(
    [
        np.full(columns.stop - columns.start, CHANNEL_DEFAULTS.get(name, np.nan))
        for name, columns in PACKED_COLUMNS.items()
    ]
)
PACKED_DEFAULTS.flags.writeable = False

#: a sample's named inputs beside its drive readings: channel → value (a float or an array)
Inputs = Mapping[str, "np.ndarray | float"]


def packed_inputs(inputs: Mapping) -> np.ndarray:
    """A sample's channels as one flat vector, every channel of :data:`CHANNEL_SHAPES` in order, at
    :data:`CHANNEL_DEFAULTS` (else NaN) where the sample lacks it: how a buffer of samples keeps them.

    Called for every sample a batch method buffers, so it writes the channels a sample has into a
    copy of :data:`PACKED_DEFAULTS` rather than building an array for every channel and joining them."""
    packed = PACKED_DEFAULTS.copy()
    for name, columns in PACKED_COLUMNS.items():
        value = inputs.get(name)
        if value is not None:
            packed[columns] = np.ravel(np.asarray(value, dtype=float))
    return packed


def unpacked_inputs(packed: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`packed_inputs` of ``N`` samples ``(N, PACKED_WIDTH)`` back to a log's channels, those
    that no sample had (all NaN) left out."""
    channels = {}
    for name, columns in PACKED_COLUMNS.items():
        values = np.asarray(packed[:, columns], dtype=float).reshape(len(packed), *CHANNEL_SHAPES[name])
        if not np.all(np.isnan(values)):
            channels[name] = values
    return channels


def with_payload(inputs: Inputs | None, extra_kg: float) -> dict:
    """``inputs`` with ``extra_kg`` more payload on every sample (an estimated payload the log does not
    announce, on top of its ``load_kg``)."""
    channels = dict(inputs or {})
    if extra_kg:
        channels[LOAD_KG] = np.asarray(channels.get(LOAD_KG, 0.0), dtype=float) + extra_kg
    return channels


def broadcast_inputs(inputs: Inputs | None, n: int) -> dict[str, np.ndarray]:
    """Every channel of ``inputs`` (a scalar or one value a channel applies to all) as ``(n, ...)`` rows."""
    return {
        name: np.broadcast_to(np.asarray(value, dtype=float), (n, *CHANNEL_SHAPES.get(name, np.shape(value))))
        for name, value in (inputs or {}).items()
    }


def input_rows(inputs: Mapping[str, np.ndarray], index) -> dict[str, np.ndarray]:
    """The rows ``index`` (a mask, slice, index array or integer) of every channel of a log's ``inputs``."""
    return {name: values[index] for name, values in inputs.items()}


@dataclass(frozen=True)
class Sample:
    """One measurement: executed drive strokes and the instrument's reading at time ``t_s``.

    Attributes:
        t_s: time [s].
        strokes: ``(legs,)`` drive strokes q_i (six on the paper's drive) as executed (encoders) [mm].
        readings: ``(M,)`` the instrument's measurement z in the order of its model's ``columns``
            (:mod:`stewart_calib.instruments`), code units: for the in-situ tracker the six
            grating readings s_i [mm].
        desired_pose: ``(6,)`` pose the controller was asked for ``[mm, rad]``, or None.
        stage: free label of the experiment stage ("" when absent).
        inputs: the sample's named input channels (:data:`LOAD_KG`, :data:`TEMPERATURE_C`,
            :data:`GRAVITY`): what the drive's terms read (:class:`~stewart_calib.model.drive.DriveModel`),
            empty where the log carries none.
    """

    t_s: float
    strokes: np.ndarray
    readings: np.ndarray
    desired_pose: np.ndarray | None = None
    stage: str = ""
    inputs: Inputs = field(default_factory=dict)


@dataclass
class Log:
    """A measurement log as arrays (spec §3), N samples.

    Attributes:
        t_s: ``(N,)`` [s], non-decreasing.
        strokes: ``(N, legs)`` q_i [mm].
        readings: ``(N, M)`` the instrument's measurements (tracker: s_i [mm]).
        desired_poses: ``(N, 6)`` ``[mm, rad]`` or None when the log has no pose columns.
        stages: N labels or None.
        inputs: the named input channels, each ``(N, ...)`` (see :class:`Sample`).
        skipped: ``(row, reason)`` of rows skipped on reading (1-based file line numbers).
    """

    t_s: np.ndarray
    strokes: np.ndarray
    readings: np.ndarray
    desired_poses: np.ndarray | None = None
    stages: list[str] | None = None
    inputs: dict[str, np.ndarray] = field(default_factory=dict)
    skipped: list[tuple[int, str]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t_s)

    def __getitem__(self, k: int) -> Sample:
        return Sample(
            float(self.t_s[k]),
            self.strokes[k],
            self.readings[k],
            None if self.desired_poses is None else self.desired_poses[k],
            "" if self.stages is None else self.stages[k],
            input_rows(self.inputs, k),
        )

    def __iter__(self):
        """``self[0], self[1], …`` built column-wise (a streamed calibration makes one a sample)."""
        n = len(self)
        return map(
            Sample,
            self.t_s.tolist(),
            self.strokes,
            self.readings,
            repeat(None, n) if self.desired_poses is None else self.desired_poses,
            repeat("", n) if self.stages is None else self.stages,
            (input_rows(self.inputs, k) for k in range(n)),
        )

    @classmethod
    def concatenate(cls, logs: list[Log]) -> Log:
        """The samples of ``logs`` (at least one, all with the same optional fields and input channels)
        one after the other."""
        first = logs[0]

        def joined(name: str) -> np.ndarray:
            return np.concatenate([getattr(log, name) for log in logs])

        def joined_optional(name: str) -> np.ndarray | None:
            return None if getattr(first, name) is None else joined(name)

        return cls(
            joined("t_s"),
            joined("strokes"),
            joined("readings"),
            joined_optional("desired_poses"),
            None if first.stages is None else [s for log in logs for s in log.stages or ()],
            {name: np.concatenate([log.inputs[name] for log in logs]) for name in first.inputs},
            [row for log in logs for row in log.skipped],
        )

    def select(self, mask_or_index) -> Log:
        """A sub-log of the rows picked by a boolean mask, slice or index array."""
        pick = lambda a: None if a is None else a[mask_or_index]  # noqa: E731
        stages = None if self.stages is None else list(np.asarray(self.stages, dtype=object)[mask_or_index])
        return Log(
            self.t_s[mask_or_index],
            self.strokes[mask_or_index],
            self.readings[mask_or_index],
            pick(self.desired_poses),
            stages,
            input_rows(self.inputs, mask_or_index),
        )


@dataclass(frozen=True)
class Truth:
    """The simulator's truth for a log, row for row (spec §4).

    Attributes:
        t_s: ``(N,)`` [s].
        params: ``(N, n_params)`` true absolute drive parameters [mm], paper order.
        true_poses: ``(N, 6)`` true pose ``[mm, rad]``, or None.
        drive_terms: the true values ``(legs,)`` of the drive's terms by the drive model's block key
            (:class:`~stewart_calib.model.drive.LegTerm`; spec §7: the stroke scale k_i); a term the truth
            does not give is absent.
        instrument: ``(names, values)`` of the true outside instrument's unknowns in file units
            (frame and target(s), spec §7), or an in-situ tracker's own 42 values off their nominal
            (``z1x … ls6`` [mm], spec §4), or None.
        unloaded: ``(n_params,)`` an elastic robot's drive with no force on its legs [mm] (spec §10: what an
            elastic calibration estimates, its compliance beside it; ``params`` are that drive loaded at each
            sample), or None (a rigid robot: ``params`` are its drive).
    """

    t_s: np.ndarray
    params: np.ndarray
    true_poses: np.ndarray | None = None
    drive_terms: dict[str, np.ndarray] = field(default_factory=dict)
    instrument: tuple[tuple[str, ...], np.ndarray] | None = None
    unloaded: np.ndarray | None = None


#: a sample whose strokes are all within this of a held pose's first sample's [mm] reads that pose again (a
#: thousandth of a hexapod's stroke, a hundred times its encoders' noise)
HOLD_MM = 0.1
#: the samples of one held pose a :class:`HeldPoseSamples` counts: a robot that rests at home for a minute
#: before it moves would fill a log's first samples with one pose
HELD_SAMPLES = 50


class HeldPoseSamples:
    """A log's first ``count`` samples, each held pose's samples past its first :data:`HELD_SAMPLES` left
    out, among its first ``limit`` (none: all), picked as the samples come: what a look at a log's start
    reads of its motion, however long the robot rested first. A sample whose strokes are all within
    :data:`HOLD_MM` of the current pose's first sample's holds that pose, any other starts the next (a slow
    motion leaves its first sample within a few samples).

    Attributes:
        indices: the picked samples' indices in the log.
        seen: the samples looked at.
        poses: the held poses among them.
    """

    def __init__(self, count: int, limit: int | None = None) -> None:
        self.count, self.limit = count, limit
        self.indices: list[int] = []
        self.seen = 0
        self.poses = 0
        self._first: np.ndarray | None = None
        self._held = 0

    @property
    def complete(self) -> bool:
        """Whether no more samples need be looked at."""
        return len(self.indices) >= self.count or (self.limit is not None and self.seen >= self.limit)

    def add(self, strokes: np.ndarray) -> bool:
        """Look at the next samples' strokes ``(n, legs)`` [mm]; whether the pick is then complete."""
        k = 0
        while k < len(strokes) and not self.complete:
            if self._first is None or np.max(np.abs(strokes[k] - self._first)) > HOLD_MM:
                self._first, self._held = strokes[k], 0
                self.poses += 1
            end = len(strokes) if self.limit is None else min(len(strokes), k + self.limit - self.seen)
            held = self._held_run(strokes[k:end])
            taken = max(0, min(held, HELD_SAMPLES - self._held, self.count - len(self.indices)))
            self.indices.extend(range(self.seen, self.seen + taken))
            self._held += held
            self.seen += held
            k += held
        return self.complete

    def _held_run(self, strokes: np.ndarray) -> int:
        """How many of ``strokes``' first samples hold the current pose (the first does), looked at in windows
        that double: a moving log's pose changes every sample, a resting robot's once in thousands."""
        start, window = 1, 1
        while start < len(strokes):
            away = np.max(np.abs(strokes[start : start + window] - self._first), axis=1) > HOLD_MM
            if away.any():
                return start + int(np.argmax(away))
            start, window = start + window, 2 * window
        return len(strokes)
