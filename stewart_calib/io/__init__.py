"""Files at the edge (spec §3–§6): measurement logs, pose lists and truth files (:mod:`.logs`),
results and traces (:mod:`.results`), all written atomically (:mod:`.atomic`).

Files hold mm and degrees; the arrays returned hold mm and rad. Every refusal is a
:class:`~stewart_calib.errors.CalibError` with one line naming the file, the row or key, and
what was expected; a failed write never leaves a partial file behind.
"""

from .atomic import BackgroundWriter, atomic_path, atomic_write_bytes, atomic_write_text
from .tables import csv_text, write_csv_blocks
from .logs import (
    LOG_REQUIRED,
    MEASURED_ANGLE_COLUMNS,
    POSE_COLUMNS,
    READING_COLUMNS,
    STROKE_COLUMNS,
    STROKE_SCALE_NAMES,
    TRUE_POSE_COLUMNS,
    LogRowParser,
    log_text,
    reading_columns,
    blank_reading_columns,
    readings_in_file_units,
    readings_to_file,
    read_log,
    read_log_blocks,
    read_pose_list,
    read_pose_list_blocks,
    read_truth,
    truth_text,
    write_log,
    write_pose_list,
    write_pose_list_blocks,
    write_truth,
)
from .results import (
    NOMINAL_TOLERANCE_MM,
    RESULT_FORMAT,
    RESULT_SUM_TOLERANCE_MM,
    read_calibrated_drive,
    read_result,
    result_dict,
    result_text,
    trace_text,
    validate_result,
    write_result,
    write_trace,
)

__all__ = [
    "LOG_REQUIRED", "MEASURED_ANGLE_COLUMNS", "STROKE_SCALE_NAMES", "reading_columns", "readings_to_file", "readings_in_file_units", "blank_reading_columns", "csv_text", "write_csv_blocks",
    "NOMINAL_TOLERANCE_MM", "POSE_COLUMNS", "READING_COLUMNS", "RESULT_FORMAT",
    "RESULT_SUM_TOLERANCE_MM", "STROKE_COLUMNS", "TRUE_POSE_COLUMNS", "BackgroundWriter", "LogRowParser", "atomic_path", "atomic_write_bytes",
    "atomic_write_text", "read_calibrated_drive", "read_log", "read_log_blocks", "read_pose_list", "read_pose_list_blocks", "read_result", "read_truth",
    "log_text", "result_dict", "result_text", "trace_text", "truth_text", "validate_result", "write_log", "write_pose_list", "write_pose_list_blocks",
    "write_result", "write_trace", "write_truth",
]
