"""``track --link`` (spec §16): samples from a controller, the estimate written back.

The controllers are real servers inside this process on 127.0.0.1 (tests/controllers.py): an
``asyncua`` OPC UA server and pyads's ADS test server, publishing a simulated log row by row under
a sample counter.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import read_log, read_result, write_log
from stewart_calib.io.logs import LOG_REQUIRED
from stewart_calib.samples import Log
from stewart_calib.workflows.calibration import run_calibration
from tests.synthetic import NIM_STEWART, nim_stewart, tracked_log

pytest.importorskip("asyncua")

N = 40
COLUMNS = list(LOG_REQUIRED)
WRITES = {"parameters": 42, "stddev": 42, "samples_used": 1}
#: the arrays the test controller holds: the estimate's, and one of another length
ARRAYS = {**WRITES, "short": 41}


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
        [
            "track",
            "--platform",
            str(NIM_STEWART),
            "--method",
            "ekf",
            "--link",
            str(link_path),
            "--out",
            str(out),
            *map(str, argv),
        ]
    )
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.fixture(scope="module")
def opcua():
    """One server for the module (its start-up loads OPC UA's standard address space: ~5 s)."""
    from tests.controllers import OpcUaController

    controller = OpcUaController(COLUMNS, ARRAYS)
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


def test_a_counter_jump_counts_the_samples_missed_and_uses_only_those_read(opcua, rows, tmp_path, capsys):
    gone = {10, 11, 12}
    code, err, out = _run_with(opcua, rows, tmp_path, capsys, skip=lambda k: k in gone)
    assert code == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_missed"]) == (N - 3, 3)
    assert err[-1].endswith(f"of {N - 3} rows; 3 samples missed)")
    kept = [k for k in range(N) if k not in gone]
    assert_equal_to_rounding(result["error"], run_calibration(nim_stewart(), _log_of(rows[kept]), "ekf").estimate.error)


def test_a_resumed_link_reads_no_sample_twice(opcua, rows, tmp_path, capsys):
    from tests.controllers import publisher

    link, out, ckpt = tmp_path / "L.toml", tmp_path / "r.json", tmp_path / "c.npz"
    link.write_text(opcua.link(WRITES))
    thread = publisher(opcua, rows[:25])
    assert _track(capsys, link, out, "--idle-timeout", "1", "--checkpoint", ckpt, "--every", "10")[0] == 0
    thread.join(5)
    assert read_result(out)["samples_used"] == 25
    # the controller still shows sample 25 when the second run starts: it is not read again
    thread = publisher(opcua, rows[25:], first_counter=26)
    code, err = _track(capsys, link, out, "--idle-timeout", "1", "--checkpoint", ckpt, "--every", "10")
    thread.join(5)
    assert code == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_missed"]) == (N, 0)
    assert_equal_to_rounding(result["error"], run_calibration(nim_stewart(), _log_of(rows), "ekf").estimate.error)
    assert opcua.written("parameters") == result["estimate"]
    # a log file is not the link the checkpoint read: refused, not resumed at some row of it
    write_log(tmp_path / "log.csv", _log_of(rows))
    code = cli.main(
        ["track", "--platform", str(NIM_STEWART), "--method", "ekf", "--log", str(tmp_path / "log.csv")]
        + ["--out", str(tmp_path / "f.json"), "--checkpoint", str(ckpt)]
    )
    assert code != 0 and "not the log the checkpoint read (opc.tcp://" in capsys.readouterr().err


def test_a_dropped_connection_is_retried_and_its_gap_reported(opcua, rows, tmp_path, capsys):
    link, out = tmp_path / "L.toml", tmp_path / "r.json"
    link.write_text(opcua.link(WRITES))

    opcua.publish(rows[0], 1)

    def controller() -> None:
        for k in range(1, 15):
            opcua.publish(rows[k], k + 1)
        opcua.drain()
        opcua.stop()  # the link goes down; the controller's cycle goes on
        for k in range(15, 20):
            opcua.publish(rows[k], k + 1, handshake=False)
        # the sample the link finds when it is back, published before it can be: whenever the
        # link reconnects, its first poll sees counter 21 (not 20, had it come back between the
        # restart and this publish), and the next is published only once that poll has seen it
        opcua.publish(rows[20], 21)
        opcua.restart()
        for k in range(21, N):
            opcua.publish(rows[k], k + 1)
        opcua.drain()

    thread = threading.Thread(target=controller, daemon=True)
    thread.start()
    code, err = _track(capsys, link, out, "--idle-timeout", "3")
    thread.join(5)
    assert code == 0, err
    lost = [line for line in err if "lost the link" in line]
    back = [line for line in err if "is back after" in line]
    assert len(lost) == 1 and len(back) == 1, err
    assert back[0].endswith("5 samples missed (counter 15 → 21)"), back
    result = read_result(out)
    assert (result["samples_used"], result["samples_missed"]) == (N - 5, 5)
    kept = [*range(15), *range(20, N)]
    assert_equal_to_rounding(result["error"], run_calibration(nim_stewart(), _log_of(rows[kept]), "ekf").estimate.error)
    assert opcua.written("parameters") == result["estimate"]


def _names(opcua, **changed):
    names = {column: opcua.node("Robot." + column) for column in COLUMNS}
    return {**names, **changed}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"read": {"q3_mm": "ns=2;s=Robot.q7_mm"}},
            "read.q3_mm = 'ns=2;s=Robot.q7_mm': not on the controller (BadNodeIdUnknown); "
            "expected a variable it publishes",
        ),
        (
            {"read": {"s2_mm": "ns=2;s=Robot.Name"}},
            "read.s2_mm = 'ns=2;s=Robot.Name': the controller declares String; expected a number (a scalar)",
        ),
        (
            {"write": {"parameters": "ns=2;s=Calib.short"}},
            "write.parameters = 'ns=2;s=Calib.short': an array of 41 on the controller; the estimate has 42",
        ),
        (
            {"write": {"samples_used": "ns=2;s=Calib.stddev"}},
            "write.samples_used = 'ns=2;s=Calib.stddev': the controller declares Double array; "
            "expected a number (a scalar)",
        ),
        (
            {"write": {"stddev": "ns=2;s=Robot.q1_mm"}},
            "write.stddev = 'ns=2;s=Robot.q1_mm': the controller declares Double; expected an array of numbers",
        ),
    ],
)
def test_a_variable_missing_or_of_another_type_is_refused_in_one_line_naming_it(
    opcua, tmp_path, capsys, change, message
):
    from tests.controllers import link_toml

    writes = {key: opcua.node("Calib." + key) for key in WRITES}
    text = link_toml(
        opcua.url,
        _names(opcua, **change.get("read", {})),
        opcua.node("Robot.Sample"),
        {**writes, **change.get("write", {})},
    )
    link, out = tmp_path / "L.toml", tmp_path / "r.json"
    link.write_text(text.replace("ns=2;", f"ns={opcua.ns};"))
    code, err = _track(capsys, link, out, "--idle-timeout", "1")
    assert code != 0 and err == [f"stewart-calib track: error: {link}: {message.replace('ns=2;', f'ns={opcua.ns};')}"]
    assert not out.exists()


def test_a_sample_that_is_not_finite_follows_the_log_rules(opcua, rows, tmp_path, capsys):
    bad = rows.copy()
    bad[5, 9] = np.nan  # s3_mm of the sixth sample
    code, err, out = _run_with(opcua, bad, tmp_path, capsys, "--skip-bad-rows")
    assert code == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_skipped"], result["samples_missed"]) == (N - 1, 1, 0)
    assert err[0].startswith(
        f"stewart-calib track: skipped bad log rows: 1 of {N} (first: {tmp_path / 'L.toml'}: row 7"
    )
    kept = [k for k in range(N) if k != 5]
    assert_equal_to_rounding(result["error"], run_calibration(nim_stewart(), _log_of(rows[kept]), "ekf").estimate.error)


@pytest.fixture(scope="module")
def ads():
    """One server for the module: the client library fixes its port, which a closed server holds a while."""
    pytest.importorskip("pyads")
    from tests.controllers import AdsController

    controller = AdsController(COLUMNS, ARRAYS)
    yield controller
    controller.close()


def test_ads_link_reads_by_sum_read_and_writes_back_calibrates_estimate(ads, rows, tmp_path, capsys):
    gone = {20}
    code, err, out = _run_with(ads, rows, tmp_path, capsys, "--every", "9", skip=lambda k: k in gone)
    assert code == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_missed"]) == (N - 1, 1)
    kept = [k for k in range(N) if k not in gone]
    assert_equal_to_rounding(result["error"], run_calibration(nim_stewart(), _log_of(rows[kept]), "ekf").estimate.error)
    assert ads.written("parameters") == result["estimate"]
    assert ads.written("stddev") == result["stddev"]
    assert ads.written("samples_used") == N - 1


def test_ads_a_missing_symbol_is_refused_in_one_line_naming_it(ads, tmp_path, capsys):
    link, out = tmp_path / "L.toml", tmp_path / "r.json"
    link.write_text(ads.link(WRITES).replace('"Robot.s4_mm"', '"Robot.s4mm"'))
    code, err = _track(capsys, link, out, "--idle-timeout", "1")
    assert code != 0 and err[0] == (
        f"stewart-calib track: error: {link}: read.s4_mm = 'Robot.s4mm': not on the controller (ADS error 1808); "
        "expected a symbol the PLC program declares"
    )
