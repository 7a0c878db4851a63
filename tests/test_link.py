"""``track --link`` (spec §16): samples from a controller, the estimate written back.

The controllers are real servers inside this process on 127.0.0.1 (tests/controllers.py): an
``asyncua`` OPC UA server and pyads's ADS test server, publishing a simulated log row by row under
a sample counter.
"""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.calibration import run_calibration
from stewart_calib.io import read_log, read_result, write_log
from stewart_calib.io.logs import LOG_REQUIRED
from stewart_calib.samples import Log
from tests.synthetic import NIM_STEWART, nim_stewart, tracked_log

pytest.importorskip("asyncua")

N = 40
COLUMNS = list(LOG_REQUIRED)
WRITES = {"parameters": 42, "stddev": 42, "samples_used": 1}


def assert_equal_to_rounding(actual, expected) -> None:
    """As tests/test_track_cli.py: track folds rows in through ekf's compiled block recursion,
    ``calibrate`` in memory may take another compilation of it (measured ≤ 2e-12 mm on δM)."""
    np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    """The log's rows as a controller publishes them: the values of its CSV file, column by column."""
    path = tmp_path_factory.mktemp("log") / "log.csv"
    write_log(path, tracked_log(11, N))
    log = read_log(path)
    return np.column_stack([log.t_s, log.strokes, log.readings])


def _log_of(rows: np.ndarray) -> Log:
    return Log(rows[:, 0], rows[:, 1:7], rows[:, 7:13])


def _track(capsys, link_path, out, *argv):
    code = cli.main(
        ["track", "--platform", str(NIM_STEWART), "--method", "ekf", "--link", str(link_path), "--out", str(out), *argv]
    )
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.fixture
def opcua():
    from tests.controllers import OpcUaController

    controller = OpcUaController(COLUMNS, WRITES)
    yield controller
    controller.close()


def _run_with(controller, rows, tmp_path, capsys, *argv, skip=lambda k: False, writes=tuple(WRITES)):
    from tests.controllers import publisher

    link = tmp_path / "L.toml"
    link.write_text(controller.link(writes))
    out = tmp_path / "r.json"
    thread = publisher(controller, rows, skip=skip)
    code, err = _track(capsys, link, out, "--idle-timeout", "1", *argv)
    thread.join(5)
    assert not thread.is_alive()
    return code, err, out


def test_opcua_link_reads_every_row_and_writes_back_calibrates_estimate(opcua, rows, tmp_path, capsys):
    code, err, out = _run_with(opcua, rows, tmp_path, capsys, "--every", "7")
    assert code == 0, err
    result = read_result(out)
    assert result["samples_used"] == N and result["samples_missed"] == 0 and result["final"] is True
    expected = run_calibration(nim_stewart(), _log_of(rows), "ekf").estimate
    assert_equal_to_rounding(result["error"], expected.error)
    # what the controller holds is the result, value for value
    assert opcua.written("parameters") == result["estimate"]
    assert opcua.written("stddev") == result["stddev"]
    assert opcua.written("samples_used") == N
