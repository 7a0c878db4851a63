"""Online calibration beside a running robot: :class:`OnlineCalibrator` and checkpoints.

For users who embed the estimator in their controller's processing unit::

    calib = OnlineCalibrator(platform, "ekf")          # or OnlineCalibrator.load("ckpt.npz", platform)
    for sample in stream:
        try:
            calib.update(sample)                        # SampleRejected: counted, state untouched
        except SampleRejected:
            pass
        strokes = calib.compensated_strokes(pose_mm_deg)  # IK of the estimated model (angles in degrees)
    calib.save("ckpt.npz")

A sample that cannot be used (non-finite, outside the platform's ranges, FK not converging,
gated as an outlier, gtsam failing in the ``isam2`` update) raises
:class:`~stewart_calib.errors.SampleRejected`, leaves the estimator as it was, and is counted
by reason (:class:`Rejections`, the result's added ``samples_rejected`` field).

Checkpoint format (``.npz``, written atomically, read with ``allow_pickle=False``): arrays
``format`` (``"stewart-calib/checkpoint"``), ``version`` (:data:`CHECKPOINT_VERSION`),
``method``, ``platform_toml`` (the platform, spec §2, exact round trip), ``config_json``
(the estimator config), the stream counters, and the estimator's ``export_state()`` flattened
to ``state/<key>/<key>`` arrays. Floats are stored as float64 bits, so the EKFs resume
exactly; ``isam2`` is rebuilt from its window prior and replay buffer
(:meth:`~stewart_calib.estimators.isam2.ISAM2Estimator.export_state`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import tomllib
import zipfile
import zlib
from collections import Counter
from io import BytesIO
from pathlib import Path

import numpy as np

from .. import io
from ..analysis.compensation import compensate
from ..analysis.plausibility import check_plausible
from ..config import EstimatorConfig, config_from_dict, load_estimator_config
from ..errors import CalibError, SampleRejected, shown
from ..estimate import Estimate, model_estimate
from ..estimators import method_names, method_spec
from ..estimators.base import (
    CheckpointableEstimator,
    accounted_estimate,
    readmitted_count,
    skipped_count,
    take_late_rejections,
    update_block,
)
from ..inputs import read_input_bytes
from ..io.platform_file import load_platform, parse_platform, platform_to_toml
from ..model.drive import PAYLOAD, drive_model
from ..model.platform import Platform
from ..samples import Inputs, Log, Sample, with_payload

CHECKPOINT_FORMAT = "stewart-calib/checkpoint"
CHECKPOINT_VERSION = 1

#: methods that update per sample and can be checkpointed (from the estimator registry).
ONLINE_METHODS = method_names(online=True, checkpointable=True)

#: accepted samples kept for the plausibility check of :meth:`OnlineCalibrator.result` (not
#: checkpointed: after a resume the check sees the samples since).
RECENT_SAMPLES = 100


class Rejections:
    """Counts of rejected samples by reason, and the first message (bounded memory)."""

    def __init__(self, count: int = 0, by_reason: dict | None = None, first: str = ""):
        self.count = count
        self.by_reason = Counter(by_reason or {})
        self.first = first

    @classmethod
    def of(cls, errors) -> Rejections:
        """Counts of the :class:`SampleRejected` ``errors`` by their ``reason``."""
        rejections = cls()
        for err in errors:
            rejections.add(err)
        return rejections

    def add(self, err: SampleRejected) -> None:
        self.by_reason[err.reason] += 1
        self.count += 1
        self.first = self.first or str(err)

    def summary(self) -> dict:
        """Every refusal by reason and the first one's message (a checkpoint's record, which a resumed run adds to)."""
        return {"count": self.count, "by_reason": dict(sorted(self.by_reason.items())), "first": self.first or None}

    def in_result(self, estimate: Estimate) -> dict:
        """The result's ``samples_rejected`` field (added to spec §5): the samples refused and not taken back in
        by ``estimate``'s method (:func:`~stewart_calib.estimators.base.readmitted_count`, gated outliers each),
        the count ``samples_skipped`` holds, with ``"readmitted"`` where the method took some back; ``"first"``
        is the first refusal's message."""
        readmitted = readmitted_count(estimate)
        by_reason = Counter(self.by_reason)
        by_reason[SampleRejected.GATED] -= readmitted
        field = {
            "count": self.count - readmitted,
            "by_reason": {reason: n for reason, n in sorted(by_reason.items()) if n > 0},
            "first": (self.first or None) if self.count > readmitted else None,
        }
        return {**field, "readmitted": readmitted} if readmitted else field


class RecentSamples:
    """The last ``size`` (strokes, readings) rows in a ring of two arrays: written a block at a
    time without a Python object per sample, read in order once per result."""

    def __init__(self, size: int, legs: int, width: int):
        self._strokes, self._readings = np.empty((size, legs)), np.empty((size, width))
        self._count = 0  # rows ever written; the next goes to _count % size

    def append(self, strokes: np.ndarray, readings: np.ndarray) -> None:
        """Append one row ``(legs,)``, ``(width,)`` [mm]."""
        at = self._count % len(self._strokes)
        self._strokes[at], self._readings[at] = strokes, readings
        self._count += 1

    def extend(self, strokes: np.ndarray, readings: np.ndarray) -> None:
        """Append rows ``(K, legs)`` and ``(K, width)`` [mm] (only the last ``size`` are kept)."""
        count = len(strokes)
        keep = min(count, len(self._strokes))
        at = np.arange(self._count + count - keep, self._count + count) % len(self._strokes)
        self._strokes[at], self._readings[at] = strokes[count - keep :], readings[count - keep :]
        self._count += count

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The rows kept, oldest first."""
        size = len(self._strokes)
        order = np.arange(self._count - min(self._count, size), self._count) % size
        return self._strokes[order], self._readings[order]


def _make(method: str, platform: Platform, config: EstimatorConfig) -> CheckpointableEstimator:
    estimator = method_spec(method, ONLINE_METHODS, "online method").build(platform, config)
    if not isinstance(estimator, CheckpointableEstimator):
        raise TypeError(f"online method '{method}' exports no state: it cannot be checkpointed")
    return estimator


class OnlineCalibrator:
    """One online estimator with rejection bookkeeping and checkpoints.

    Args:
        platform: the nominal platform (spec §2), or its file's path or shipped name.
        method: ``paper-ekf``, ``ekf`` or ``isam2``.
        config: estimator settings (default: the defaults), or a config file's path or shipped
            name (``"paper"``).

    Not thread-safe: one thread at a time may call its methods (two threads calling
    :meth:`update` at once corrupt the state); give each thread its own, or lock around it.

    Attributes:
        rows_read, rows_skipped: the caller's stream position (data rows consumed, bad rows
            skipped); saved and restored with the checkpoint so a resumed reader knows where
            it stands (``track`` uses them).
        rejections: samples the estimator refused, by reason.
        source: what identifies the log file being read (``track``: its path, device, inode and
            size, the SHA-256 of its header and first lines, the rows read of it), saved with the
            checkpoint so a resume can tell the same log from another; None when not known.
    """

    def __init__(
        self, platform: Platform | str | Path, method: str, config: EstimatorConfig | str | Path | None = None
    ):
        if isinstance(platform, (str, Path)):
            platform = load_platform(platform)
        if not isinstance(platform, Platform):
            raise CalibError(f"platform: expected a Platform or a platform file's path, got {type(platform).__name__}")
        if isinstance(config, (str, Path)):
            config = load_estimator_config(config)
        if config is not None and not isinstance(config, EstimatorConfig):
            raise CalibError(
                f"config: expected an EstimatorConfig or a config file's path, got {type(config).__name__}"
            )
        self.platform = platform
        self.method = method
        self.config = config or EstimatorConfig()
        self._estimator = _make(method, platform, self.config)
        self._width = len(io.reading_columns(platform))  # the instrument's values in a row
        # the layout is fixed at construction: whether compensation needs the drive's identified blocks
        self._drive = drive_model(platform)
        layout = self._estimator.estimate().layout
        self._identifies_drive_blocks = any(
            layout.slice(key) is not None for key in (*(term.key for term in self._drive.terms), PAYLOAD)
        )
        self.rows_read = 0
        self.rows_skipped = 0
        self.source: dict | None = None
        self.rejections = Rejections()
        # accepted samples for the plausibility check (a leg set's residual, an outside instrument's motion)
        self._recent = RecentSamples(RECENT_SAMPLES, platform.drive.n_legs, self._width)
        self._fixed: tuple | None = None  # (what they were made of, the checkpoint's fixed arrays)

    def update(self, sample: Sample) -> None:
        """Fold in one sample.

        Raises:
            SampleRejected: with the reason; counted, and the estimator is untouched.
            CalibError: ``sample`` is no sample of this platform's log (a wrong shape or type,
                complex numbers); nothing is counted.
        """
        try:
            single = Log(np.array([sample.t_s]), np.array([sample.strokes]), np.array([sample.readings]))
        except (AttributeError, TypeError, ValueError) as err:
            raise CalibError(f"sample: not a Sample of arrays ({_one_line(err)})") from None
        _check_block_shapes(single, self.platform.drive.n_legs, self._width)
        try:
            self._estimator.update(sample)
        except SampleRejected as err:
            self.rejections.add(err)
            raise
        finally:
            for late in take_late_rejections(self._estimator):  # left out by a robust start-up batch
                self.rejections.add(late)
        self._recent.append(sample.strokes, sample.readings)

    def update_block(self, block: Log) -> list[int]:
        """Fold in every sample of ``block``: what :meth:`update` does with each in turn, the same
        state and counts, with the bookkeeping done once a block.

        The samples go through the estimator's own block path
        (:func:`~.estimators.base.update_block`: ekf's compiled recursion), as ``calibrate``'s do.

        Returns:
            The indices in ``block`` of the samples refused (counted, as :meth:`update` counts them).
        Raises:
            CalibError: ``block`` is no log of this platform (shapes, types); nothing is counted.
        """
        _check_block_shapes(block, self.platform.drive.n_legs, self._width)
        refused, late = update_block(self._estimator, block)
        # in update's order: a sample's own refusal, then those refused late after it
        for _, _, err in sorted(
            [(j, 0, err) for j, err in refused] + [(j, 1, err) for j, err in late], key=lambda event: event[:2]
        ):
            self.rejections.add(err)
        accepted = np.ones(len(block), dtype=bool)
        accepted[[j for j, _ in refused]] = False
        self._recent.extend(np.asarray(block.strokes)[accepted], np.asarray(block.readings)[accepted])
        return [j for j, _ in refused]

    def estimate(self) -> Estimate:
        """δM [mm] and covariance after the last accepted sample (its details account for the
        samples it does not count as used: :func:`~.estimators.base.row_accounting`)."""
        return accounted_estimate(self._estimator)

    def compensated_strokes(self, pose_mm_deg: np.ndarray, inputs: Inputs | None = None) -> np.ndarray:
        """Strokes [mm] that put the estimated drive at ``pose_mm_deg`` ``[x, y, z [mm], roll, pitch, yaw [deg]]``
        (``(6,)`` or ``(N, 6)``): a pose in the units of every file (spec §1), the row of a pose list
        or of ``compensate --poses -``. :meth:`compensated_strokes_rad` takes the angles in radians.
        ``inputs`` are the channels the poses are commanded at, e.g. the legs warm at 28 °C on a
        platform with ``[thermal]`` (spec §17), as ``compensate --temperature-C 28`` takes them::

            calibrator.compensated_strokes(pose, {"temperature_C": np.full(6, 28.0)})

        Raises:
            as :meth:`compensated_strokes_rad`.
        """
        pose = np.array(pose_mm_deg, dtype=float)  # a copy: the caller's array is not converted
        pose[..., 3:] = np.radians(pose[..., 3:])
        return self.compensated_strokes_rad(pose, inputs)

    def compensated_strokes_rad(self, pose_mm_rad: np.ndarray, inputs: Inputs | None = None) -> np.ndarray:
        """Strokes [mm] that put the estimated drive at ``pose_mm_rad`` ``[x, y, z [mm], roll, pitch, yaw [rad]]``
        (``(6,)`` or ``(N, 6)``; paper Fig. 3 step 4), under the input channels ``inputs`` (e.g.
        ``{"load_kg": 20.0, "temperature_C": 25.0}``, each a scalar or ``(N, ...)``; a drive without
        the term ignores its channel: :func:`~stewart_calib.analysis.compensation.compensate`), plus
        the payload the estimator found beyond the announced one (``[elastic] payload_sigma_kg``).

        Raises:
            PoseOutOfRange: a pose outside the platform's workspace, or needing a stroke outside
                its stroke range — the same checks and error type as ``stewart-calib compensate``
                (:func:`~stewart_calib.analysis.compensation.check_reachable`).
            CalibError: non-finite poses or a wrong shape.
        """
        if not self._identifies_drive_blocks:
            drive = self._drive.calibrated(self._estimator.current_error(), {})
            return compensate(drive, pose_mm_rad, limits=self.platform, inputs=inputs)
        estimate = model_estimate(self._estimator)
        loaded = with_payload(inputs, estimate.unannounced_payload_kg())
        return compensate(self._drive.calibrated_by(estimate), pose_mm_rad, limits=self.platform, inputs=loaded)

    def result(self) -> dict:
        """The current estimate as a spec §5 result, with the added ``samples_rejected`` field.

        ``samples_skipped`` counts bad rows skipped and samples rejected, as ``calibrate`` does.

        Raises:
            CalibError: the estimate is not credible for this platform (a log of another
                platform; :func:`~stewart_calib.analysis.plausibility.check_plausible` on the last
                :data:`RECENT_SAMPLES` accepted samples).
        """
        estimate = self.estimate()
        strokes, readings = self._recent.arrays()
        noise_scale = getattr(self._estimator, "noise_scale", lambda: None)()
        check_plausible(self.platform, estimate.error, self.config.noise, strokes, readings, self.method, noise_scale)
        skipped = skipped_count(self.rows_skipped, self.rejections.count, estimate)
        return io.result_dict(
            estimate, self.platform, skipped, {"samples_rejected": self.rejections.in_result(estimate)}
        )

    def export_state(self) -> dict:
        """The estimator's state (nested dict of arrays); equal states give equal futures."""
        return self._estimator.export_state()

    def save(self, path: str | Path) -> None:
        """Write a checkpoint atomically (see the module docstring)."""
        io.atomic_write_bytes(path, self.checkpoint_bytes())

    def checkpoint_bytes(self) -> bytes:
        """What :meth:`save` writes: the checkpoint of the state now, a file's bytes."""
        arrays = {
            **self._fixed_arrays(),
            "rows_read": np.array(self.rows_read),
            "rows_skipped": np.array(self.rows_skipped),
            "rejections_json": np.array(json.dumps(self.rejections.summary())),
            **({} if self.source is None else {"source_json": np.array(json.dumps(self.source))}),
            **_flatten(self.export_state(), "state"),
        }
        return npz_bytes(arrays)

    def _fixed_arrays(self) -> dict[str, np.ndarray]:
        """The checkpoint's arrays that no sample changes (their text costs ~0.3 ms), made once."""
        made_of = (self.method, self.platform, self.config)
        if self._fixed is None or any(a is not b for a, b in zip(self._fixed[0], made_of, strict=True)):
            self._fixed = (
                made_of,
                {
                    "format": np.array(CHECKPOINT_FORMAT),
                    "version": np.array(CHECKPOINT_VERSION),
                    "method": np.array(self.method),
                    "platform_toml": np.array(platform_to_toml(self.platform, exact=True)),
                    "config_json": np.array(json.dumps(dataclasses.asdict(self.config))),
                },
            )
        return self._fixed[1]

    @classmethod
    def load(cls, path: str | Path, platform: Platform | str | Path | None) -> OnlineCalibrator:
        """Rebuild from a checkpoint written by :meth:`save`, for ``platform``.

        ``platform`` (a :class:`Platform`, or its file's path or shipped name) must be the one
        the checkpoint was written for: a checkpoint of another robot is refused, never resumed
        with its model. None takes the checkpoint's own platform (to inspect a checkpoint).

        Raises:
            CalibError: one line naming the file: missing, not a checkpoint, another format
                version, corrupt (a missing, misshapen or implausible array — a covariance
                that is not symmetric positive semi-definite, non-finite noise, an impossible
                time —, a bad platform or config), or written for another platform.
        """
        shown_path = shown(path)
        data = read_input_bytes(path, "checkpoint", MAX_CHECKPOINT_BYTES, lines=False)
        # np.load takes anything that is no archive for a pickle and then advises allow_pickle,
        # the wrong advice for a file that is simply not a checkpoint.
        if not zipfile.is_zipfile(BytesIO(data)):
            raise CalibError(
                f"{shown_path}: not a readable checkpoint (not an .npz archive written by track --checkpoint)"
            )
        try:
            _check_members(data)
            with np.load(BytesIO(data), allow_pickle=False) as npz:
                arrays = {name: npz[name] for name in npz.files}
        except CalibError as err:
            raise CalibError(f"{shown_path}: not a readable checkpoint ({err})") from None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, RecursionError, MemoryError) as err:
            raise CalibError(f"{shown_path}: not a readable checkpoint ({_one_line(err)})") from None
        try:
            calib = cls._from_arrays(arrays)
        except CalibError as err:
            raise CalibError(f"{shown_path}: corrupt checkpoint: {_one_line(err)}") from None
        except (KeyError, ValueError, TypeError, IndexError, RecursionError, tomllib.TOMLDecodeError) as err:
            raise CalibError(f"{shown_path}: corrupt checkpoint ({err.__class__.__name__}: {_one_line(err)})") from None
        if platform is not None:
            wanted = platform if isinstance(platform, Platform) else load_platform(platform)
            differ = _differing_tables(wanted, calib.platform)
            if differ:
                raise CalibError(
                    f"{shown_path}: written for platform '{shown(calib.platform.name)}', not for "
                    f"'{shown(wanted.name)}'{'' if isinstance(platform, Platform) else f' ({shown(platform)})'}: "
                    f"its {', '.join(f'[{table}]' for table in differ)} values differ"
                )
            calib.platform = wanted  # its name and description as the file now has them
        return calib

    @classmethod
    def _from_arrays(cls, arrays: dict[str, np.ndarray]) -> OnlineCalibrator:
        text = lambda key: str(arrays[key][()]) if arrays[key].dtype.kind == "U" else _wrong(key)  # noqa: E731
        if "format" not in arrays or arrays["format"].dtype.kind != "U" or text("format") != CHECKPOINT_FORMAT:
            raise CalibError(f"not a checkpoint: expected format {CHECKPOINT_FORMAT!r}")
        version = arrays.get("version")
        if (
            version is None
            or version.shape != ()
            or version.dtype.kind not in "iu"
            or int(version) != CHECKPOINT_VERSION
        ):
            raise CalibError(f"checkpoint version {version!r} is not supported: expected {CHECKPOINT_VERSION}")
        platform = parse_platform(tomllib.loads(text("platform_toml")), "platform_toml")
        config = config_from_dict(_json_table(text("config_json"), "config_json"), "config_json")
        calib = cls(platform, text("method"), config)
        calib._estimator.import_state(_unflatten(arrays, "state"))
        calib.rows_read, calib.rows_skipped = _count(arrays, "rows_read"), _count(arrays, "rows_skipped")
        if "source_json" in arrays:
            calib.source = _source_record(json.loads(text("source_json")))
        summary = json.loads(text("rejections_json"))
        calib.rejections = Rejections(int(summary["count"]), dict(summary["by_reason"]), summary["first"] or "")
        if not np.all(np.isfinite(calib.estimate().error)):
            raise CalibError("the restored estimate is not finite")
        return calib

    def check_counts(self) -> None:
        """Refuse stream counters that the estimate does not account for, as a reader that keeps
        them (``track``) leaves them: every row read is used, skipped, dropped by a lock-out recovery
        or held (:func:`~.estimators.base.row_accounting`), and the rows read of the current file are
        among those read in all. (A caller of :meth:`update` alone need not count rows.)

        Raises:
            CalibError: naming the counter and what the estimate accounts for.
        """
        estimate = self.estimate()
        fields = estimate.details or {}
        dropped = int((fields.get("recovery") or {}).get("samples_dropped", 0))
        skipped = skipped_count(self.rows_skipped, self.rejections.count, estimate)
        accounted = estimate.samples_used + skipped + dropped + int(fields.get("samples_held", 0))
        if self.rows_read != accounted:
            raise CalibError(
                f"array 'rows_read': {self.rows_read} rows read, but its estimate accounts for {accounted} "
                f"({estimate.samples_used} used, {skipped} skipped, {dropped} dropped, "
                f"{fields.get('samples_held', 0)} held); expected the counters of the state saved with them"
            )
        if self.source is not None and self.source["rows"] > self.rows_read:
            raise CalibError(
                f"array 'source_json': {self.source['rows']} rows read of {shown(str(self.source['path']))}, "
                f"more than the {self.rows_read} read in all"
            )


#: the largest checkpoint read [bytes] (a tracker's is ~0.3 MB; isam2's replay buffer a few MB).
MAX_CHECKPOINT_BYTES = 256 << 20
#: the most members a checkpoint may hold (its arrays: a few dozen).
MAX_CHECKPOINT_MEMBERS = 4096


def _check_members(data: bytes) -> None:
    """Refuse, before anything is decompressed or allocated, a checkpoint archive whose members
    would unpack to more than :data:`MAX_CHECKPOINT_BYTES` (a small deflated member can declare
    gigabytes), or whose arrays declare shapes larger than their member holds, or of objects."""
    with zipfile.ZipFile(BytesIO(data)) as archive:
        members = archive.infolist()
        if len(members) > MAX_CHECKPOINT_MEMBERS:
            raise CalibError(f"{len(members)} members; expected at most {MAX_CHECKPOINT_MEMBERS}")
        if sum(member.file_size for member in members) > MAX_CHECKPOINT_BYTES:
            largest = max(members, key=lambda member: member.file_size)
            raise CalibError(f"member '{shown(largest.filename)}' unpacks to {largest.file_size} bytes; too large")
        for member in members:
            with archive.open(member) as file:
                version = np.lib.format.read_magic(file)
                read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
                if version not in read_header:
                    raise CalibError(f"member '{shown(member.filename)}': npy format version {version} not supported")
                shape, _, dtype = read_header[version](file, max_header_size=1 << 16)
            if dtype.hasobject or math.prod(shape) * dtype.itemsize > member.file_size:
                raise CalibError(
                    f"member '{shown(member.filename)}': declares a {dtype} array of shape {shape}, more than it holds"
                )


def _check_block_shapes(block: Log, legs: int, width: int) -> None:
    """Refuse a block that is no log of a platform of ``legs`` drive legs whose instrument reads
    ``width`` values: not real numbers, or columns other than ``t_s (N,)``, strokes ``(N, legs)``,
    readings ``(N, width)``."""
    try:
        arrays = [np.asarray(values) for values in (block.t_s, block.strokes, block.readings)]
    except (TypeError, ValueError, AttributeError) as err:
        raise CalibError(f"samples: not a log of arrays ({_one_line(err)})") from None
    for name, values in zip(("t_s", "strokes", "readings"), arrays, strict=True):
        if values.dtype.kind not in "iuf":
            raise CalibError(f"samples: {name} of {values.dtype} values; expected real numbers")
    t_s, strokes, readings = arrays
    n = len(t_s) if t_s.ndim == 1 else -1
    if n < 0 or strokes.shape != (n, legs) or readings.shape != (n, width):
        raise CalibError(
            f"samples: t_s {t_s.shape}, strokes {strokes.shape}, readings {readings.shape}; "
            f"expected (N,), (N, {legs}), (N, {width})"
        )


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """What ``np.savez`` writes for ``arrays`` (an uncompressed ZIP of ``<name>.npy`` members),
    built in memory: zipfile's per-member bookkeeping cost most of the time of a checkpoint,
    which ``track`` writes every ``--every`` rows (BENCHMARKS.md). Members are dated 1980-01-01 (ZIP's
    epoch): a checkpoint's time is its file's."""
    local, central = bytearray(), bytearray()
    for name, array in arrays.items():
        buffer = BytesIO()
        np.lib.format.write_array(buffer, np.asanyarray(array), allow_pickle=False)
        data, filename = buffer.getvalue(), f"{name}.npy".encode()
        # version 2.0, no flags, stored, DOS time 00:00 date 1980-01-01, CRC-32, sizes, name length, no extra
        header = struct.pack("<HHHHHIIIHH", 20, 0, 0, 0, 0x21, zlib.crc32(data), len(data), len(data), len(filename), 0)
        central += (
            struct.pack("<IH", 0x02014B50, 20) + header + struct.pack("<HHHII", 0, 0, 0, 0, len(local)) + filename
        )
        local += struct.pack("<I", 0x04034B50) + header + filename + data
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(arrays), len(arrays), len(central), len(local), 0)
    return bytes(local + central + end)


def _source_record(record) -> dict:
    """The checkpoint's record of the log read, checked: what a resume compares."""
    ok = isinstance(record, dict) and isinstance(record.get("path"), str) and isinstance(record.get("head_sha256"), str)
    for key in ("head_lines", "rows"):
        ok = ok and type(record.get(key)) is int and 0 <= record[key] < 2**63
    if not ok:
        raise CalibError(
            "array 'source_json': expected the record of the log read (path, head_lines, head_sha256, rows)"
        )
    return record


def _differing_tables(a: Platform, b: Platform) -> list[str]:
    """The tables of the platform files ``a`` and ``b`` whose values differ. The free text
    (``name``, ``description``) is left out: a checkpoint holds the estimate of a geometry, and
    a platform renamed or described anew is the same robot."""
    tables = [
        tomllib.loads(platform_to_toml(dataclasses.replace(p, name="", description=""), exact=True)) for p in (a, b)
    ]
    return [key for key in sorted(set(tables[0]) | set(tables[1])) if tables[0].get(key) != tables[1].get(key)]


def _json_table(text: str, key: str) -> dict:
    """The JSON object of the checkpoint's array ``key`` (a config's sections)."""
    value = json.loads(text)
    if not isinstance(value, dict):
        raise CalibError(f"array '{key}': expected a JSON object of config sections, got {type(value).__name__}")
    return value


def _wrong(key: str):
    raise CalibError(f"array '{key}': expected text")


def _count(arrays: dict, key: str) -> int:
    value = arrays[key]
    if value.shape != () or value.dtype.kind not in "iu" or int(value) < 0:
        raise CalibError(f"array '{key}': expected a non-negative whole number")
    return int(value)


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or err.__class__.__name__


def _flatten(tree: dict, prefix: str) -> dict[str, np.ndarray]:
    """``{"a": {"b": x}}`` → ``{"<prefix>/a/b": array(x)}`` (npz holds flat names)."""
    out = {}
    for key, value in tree.items():
        name = f"{prefix}/{key}"
        out.update(_flatten(value, name) if isinstance(value, dict) else {name: np.asarray(value)})
    return out


def _unflatten(arrays: dict[str, np.ndarray], prefix: str) -> dict:
    tree: dict = {}
    for name, value in arrays.items():
        if not name.startswith(prefix + "/"):
            continue
        *parents, leaf = name[len(prefix) + 1 :].split("/")
        node = tree
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree
