"""The sweep on a real Dask cluster: a ``dask scheduler`` and ``dask worker`` processes on
127.0.0.1 (ports chosen by the OS), started and stopped here.

* the same sweep through the scheduler and on the embedded local cluster: identical rows;
* the client killed mid-sweep, then the same command again: no row lost, none computed twice;
* a worker killed while it runs a task: the task runs elsewhere and the sweep finishes;
* an address where no scheduler listens: one line naming it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from stewart_calib.cli import main
from stewart_calib.sweep import load_spec, run_sweep, store
from stewart_calib.sweep.task import run_task

ROOT = Path(__file__).resolve().parents[1]

#: Hang guard for processes and polls [s] (not a speed requirement).
PATIENCE_S = 120

#: Worker environment: the repository on the path, and one BLAS thread as a nanny sets it, so
#: the workers compute exactly as the local cluster's do.
WORKER_ENV = {
    **os.environ,
    "PYTHONPATH": str(ROOT),
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}

TINY = """
name = "tiny"
methods = ["ls", "ekf"]
seeds = 2
[grid]
samples = 20
reading_sigma_mm = [0.002, 0.01]
"""

#: Enough tasks (isam2: ~0.2 s each) that the client can be killed with most of them still to do.
LONGER = """
name = "longer"
methods = ["ekf", "isam2"]
seeds = 6
[grid]
samples = 20
reading_sigma_mm = [0.002, 0.01]
"""


def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "dask", *args],
        env=WORKER_ENV,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def _stop(processes: list[subprocess.Popen]) -> None:
    """Kill what the tests started (workers without a nanny and the scheduler have no children)."""
    for p in processes:
        if p.poll() is None:
            p.kill()
        p.wait()


def _wait_for(condition, what: str):
    deadline = time.monotonic() + PATIENCE_S
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"gave up waiting for {what}")


class Cluster:
    """A scheduler and workers started for the tests; ``add_worker`` starts one more."""

    def __init__(self, directory: Path):
        self.file = directory / "scheduler.json"
        self.processes = [
            _start(
                "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(self.file)
            )
        ]
        self.address = _wait_for(
            lambda: self.file.exists() and json.loads(self.file.read_text() or "{}").get("address"), "the scheduler"
        )

    def add_worker(self) -> subprocess.Popen:
        worker = _start(
            "worker",
            "--scheduler-file",
            str(self.file),
            "--nthreads",
            "1",
            "--no-nanny",
            "--no-dashboard",
            "--host",
            "127.0.0.1",
        )
        self.processes.append(worker)
        return worker

    def client(self):
        from distributed import Client

        return Client(self.address, timeout="30s", set_as_default=False)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        for _ in range(2):
            c.add_worker()
        with c.client() as client:
            client.wait_for_workers(2, timeout=PATIENCE_S)
        yield c
    finally:
        _stop(c.processes)


def _spec(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "spec.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _sweep_command(spec: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "stewart_calib", "sweep", "--spec", str(spec), "--out", str(out), *extra]


def _rows(out: Path) -> list[dict]:
    return pq.read_table(out / "results.parquet").drop_columns(["seconds", "cpu_seconds"]).to_pylist()  # timings differ


def test_scheduler_and_local_cluster_give_identical_rows(cluster, tmp_path):
    spec = load_spec(_spec(tmp_path, TINY))
    through_scheduler = run_sweep(spec, tmp_path / "remote", scheduler=cluster.address, progress=False)
    local = run_sweep(spec, tmp_path / "local", workers=2, progress=False)
    assert through_scheduler.ran == local.ran == 4 and not through_scheduler.failed
    assert len(_rows(tmp_path / "remote")) == 4 * 2
    assert _rows(tmp_path / "remote") == _rows(tmp_path / "local")


def test_resume_after_killing_the_client_loses_nothing_and_repeats_nothing(cluster, tmp_path):
    spec_path, out = _spec(tmp_path, LONGER), tmp_path / "out"
    total = len(load_spec(spec_path).tasks())
    client = subprocess.Popen(
        _sweep_command(spec_path, out, "--scheduler", cluster.address),
        env=WORKER_ENV,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_for(lambda: len(list((out / "parts").glob("*.parquet"))) >= 3, "three finished tasks")
        client.send_signal(signal.SIGKILL)
    finally:
        client.kill()
        client.wait()
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (out / "parts").glob("*.parquet")}
    assert 3 <= len(before) < total, "the client finished before it could be killed: make LONGER longer"

    again = subprocess.run(
        _sweep_command(spec_path, out, "--scheduler", cluster.address),
        env=WORKER_ENV,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=PATIENCE_S,
    )
    assert again.returncode == 0, again.stderr
    assert f"{total - len(before)} tasks run, {len(before)} already done" in again.stdout
    after = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (out / "parts").glob("*.parquet")}
    assert {name: after[name] for name in before} == before  # finished parts untouched: not computed again
    keys = [(r["cell"], r["seed"], r["method"]) for r in _rows(out)]
    assert len(keys) == len(set(keys)) == total * 2


def test_a_worker_killed_mid_task_is_replaced_and_the_sweep_finishes(cluster, tmp_path):
    spec_path, out = _spec(tmp_path, LONGER.replace('name = "longer"', 'name = "victim"')), tmp_path / "out"
    victim = cluster.add_worker()
    with cluster.client() as watcher:
        watcher.wait_for_workers(3, timeout=PATIENCE_S)
        (victim_address,) = set(watcher.scheduler_info()["workers"]) - set(_worker_addresses_except(watcher, victim))
        sweep = subprocess.Popen(
            _sweep_command(spec_path, out, "--scheduler", cluster.address),
            env=WORKER_ENV,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            _wait_for(lambda: watcher.processing(workers=[victim_address]).get(victim_address), "a task on the victim")
            os.kill(victim.pid, signal.SIGKILL)
            stdout, stderr = sweep.communicate(timeout=PATIENCE_S)
        finally:
            sweep.kill()
            sweep.wait()
    total = len(load_spec(spec_path).tasks())
    assert sweep.returncode == 0, stderr
    assert f"{total} tasks run, 0 already done, 0 failed" in stdout
    assert len(_rows(out)) == total * 2


def _worker_addresses_except(client, process: subprocess.Popen) -> list[str]:
    """Addresses of the workers other than ``process`` (matched by pid)."""
    return [address for address, pid in client.run(os.getpid).items() if pid != process.pid]


def test_unreachable_scheduler_is_one_line_with_the_address(tmp_path, capsys):
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    out = tmp_path / "out"
    assert main(["sweep", "--spec", str(_spec(tmp_path, TINY)), "--out", str(out), "--scheduler", address]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and address in err
    assert not out.exists()


def test_a_part_cut_short_is_computed_again_on_resume_and_said(tmp_path, capsys):
    """Issues 26/30: a part cut short (zero bytes, half its bytes) is no finished task: the next run
    says so, computes it again and replaces it — the same rows; a part damaged inside with its ends
    whole is named in one line when the parts are read, never a traceback."""
    spec_path = _spec(tmp_path, 'name = "cut"\nmethods = ["ls"]\nseeds = 3\n[grid]\nsamples = 20\n')
    out, spec = tmp_path / "out", load_spec(spec_path)
    command = ["sweep", "--spec", str(spec_path), "--out", str(out), "--workers", "1"]
    store.prepare(out)  # the finished sweep, without a cluster: every task's part, then the results
    for cell, seed in spec.tasks():
        store.write_part(out, run_task(cell, seed, spec.methods), store.schema(spec))
    store.consolidate(spec, out, store.schema(spec))
    rows = _rows(out)
    parts = sorted((out / "parts").glob("*.parquet"))
    assert len(parts) == 3
    whole = parts[2].read_bytes()
    parts[0].write_bytes(b"")
    parts[1].write_bytes(parts[1].read_bytes()[: len(whole) // 2])
    capsys.readouterr()
    assert main(command) == 0
    said = capsys.readouterr().out
    assert "(1 already done; 2 damaged parts computed again, first " in said and "shorter than any Parquet" in said
    assert "2 tasks run, 1 already done, 0 failed of 3" in said
    # the plan line and the summary line name the command, as every command's status lines do
    assert said.startswith("stewart-calib sweep: cut: 1 cells × 3 seeds = 3 tasks (1 already done; ")
    assert said.splitlines()[-1].startswith("stewart-calib sweep: 2 tasks run, 1 already done, 0 failed of 3;")
    assert _rows(out) == rows
    middle = len(whole) // 2
    parts[2].write_bytes(whole[:8] + bytes(b ^ 0xFF for b in whole[8:middle]) + whole[middle:])
    capsys.readouterr()
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{parts[2]}: a damaged sweep part" in err and "run the sweep again" in err


#: One task's scores, printed as JSON by a child process (the BLAS kernel and its threads are fixed
#: when numpy loads, so each setting needs a process of its own).
_TASK_SCORES = """
import json, sys
from stewart_calib.sweep import load_spec
from stewart_calib.sweep.task import run_task
spec = load_spec(sys.argv[1])
cell, seed = next(iter(spec.tasks()))
print(json.dumps([(row["rms_mm"], row["nees"]) for row in run_task(cell, seed, spec.methods)]))
"""


def _has_avx2() -> bool:
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text(encoding="utf-8")
    except OSError:
        return False


@pytest.mark.skipif(not _has_avx2(), reason="OpenBLAS's Haswell kernel needs AVX2")
def test_a_task_gives_the_same_row_whatever_the_blas_threads(tmp_path):
    """A resumed task must give the row it gave before: a Dask worker runs with one BLAS thread,
    the sweep's own process with all of them. OpenBLAS's Haswell kernel (the one Zen processors
    get too) rounds differently on one thread and on two, in the last digits of a least-squares
    fit; an AVX-512 host's kernel does not, which is why a run on such a host alone never saw it.
    So the kernel is chosen here, as those machines choose it."""
    spec_path = _spec(tmp_path, 'name = "blas"\nmethods = ["ls"]\nseeds = 1\n[grid]\nsamples = 20\n')
    scores = []
    for threads in ("1", "2"):
        env = {**os.environ, "OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_NUM_THREADS": threads}
        done = subprocess.run(
            [sys.executable, "-c", _TASK_SCORES, str(spec_path)],
            env=env,
            capture_output=True,
            text=True,
            timeout=PATIENCE_S,
            check=True,
        )
        scores.append(json.loads(done.stdout.strip().splitlines()[-1]))
    assert scores[0] == scores[1]
