"""The paper's experiment (§4) in closed loop, once per method.

* **before calibration** — :class:`NominalController` over the whole experiment (one vectorised
  pass); the paper's "before" numbers are its first (no-load) stage.
* **ls** — the paper's baseline: fitted once on the nominal run's no-load calibration segment
  (every sample of every held pose), then frozen (:class:`FrozenController`) for all stages. The
  calibration segments under load are not used by ``ls``, as in the paper (§4.2: "only the
  initial calibration under no-load conditions was performed").
* **online methods** — one :class:`EstimatorController` through the whole experiment: every
  sample is folded in and the next IK uses nominal + the latest δM.
* **online methods part by part** — :data:`LAYERED_METHODS` again, once per part of the model
  added on top of the rigid drive with the nominal tracker (``ekf+tracker``: the tracker's own
  geometry identified), each part with its own estimator settings (:class:`Part`).

Every run uses the same experiment and seed, so the desired poses, the robot and all noise
draws are identical; only the controller differs.
"""

from __future__ import annotations

import concurrent.futures
import math
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import cast

import numpy as np

from ..config import EstimatorConfig
from ..estimators import BatchEstimator, KalmanFiltered, make_estimator, method_names
from ..model.platform import Platform
from ..progress import progress_bar
from ..simulation import EstimatorController, FrozenController, NominalController, SimulationResult, run_experiment
from ..simulation.experiment import Experiment

#: the paper's batch baseline, fitted once on the no-load calibration samples.
BATCH_METHOD = "ls"
#: every online method of the registry, each run in the loop through every stage.
ONLINE_METHODS = method_names(online=True)
METHODS = (BATCH_METHOD, *ONLINE_METHODS)
#: the controller that is not calibrated at all (paper: "before calibration").
NOMINAL = "nominal"
#: online methods run again with each part of the model added (they are the ones held to the
#: paper's headline improvements).
LAYERED_METHODS = ("ekf", "isam2")


@dataclass(frozen=True)
class Part:
    """A part of the model added on top of the rigid drive with the nominal tracker.

    Attributes:
        name: the runs' suffix (``tracker`` → the run ``ekf+tracker``).
        description: what it adds, for the tables (``the tracker's geometry``).
        config: the estimator settings of the runs with this part (and those before it).
        source: where ``config`` came from, for the tables.
        platform: the platform the estimator and the controller of this part's runs (and of the
            parts after it) are given, from the experiment's; None: the experiment's own. The
            simulated robot is the experiment's in every run.
    """

    name: str
    description: str
    config: EstimatorConfig
    source: str
    platform: Callable[[Experiment], Platform] | None = None


def run_name(method: str, parts: tuple[Part, ...] = ()) -> str:
    """``ekf``, ``ekf+tracker``, …: a method with the parts of its model after the rigid drive."""
    return "+".join((method, *(part.name for part in parts)))


def fullest_run(method: str, parts: tuple[Part, ...]) -> str:
    """The run of ``method`` with every part of ``parts`` its model takes (:data:`LAYERED_METHODS`)."""
    return run_name(method, parts if method in LAYERED_METHODS else ())


def online_runs(parts: tuple[Part, ...]) -> list[tuple[str, str, tuple[Part, ...]]]:
    """``(run, method, parts of its model)`` of every online run, in order: each online method on
    the rigid model, followed for :data:`LAYERED_METHODS` by its runs with the parts added one by
    one (the last has them all)."""
    runs: list[tuple[str, str, tuple[Part, ...]]] = []
    for method in ONLINE_METHODS:
        runs.append((method, method, ()))
        if method in LAYERED_METHODS:
            runs += [(run_name(method, parts[: k + 1]), method, parts[: k + 1]) for k in range(len(parts))]
    return runs


def estimator_platform(experiment: Experiment, parts: tuple[Part, ...]) -> Platform:
    """The platform a run with ``parts`` gives its estimator: that of the last part that sets one."""
    chosen = [part.platform for part in parts if part.platform is not None]
    return chosen[-1](experiment) if chosen else experiment.platform


@dataclass(frozen=True)
class MethodRun:
    """One closed-loop run of the experiment with one method's controller.

    Attributes:
        method: ``nominal``, ``ls`` or an online method (the estimator; the run's own name is its
            key in :attr:`Reproduction.runs`).
        result: the simulated run (log, truth, desired and actual poses, stages, kinds).
        trace: ``(N, 42)`` δM the controller's IK used after each sample [mm] (paper Figs. 5–6).
        no_load_error: ``(42,)`` δM identified at no load [mm] (Table 4): ``ls``'s fit, an online
            method's estimate at the last sample of the first stage, zeros for ``nominal``.
        rejected: samples the estimator refused.
        run_time_s: wall time of the run, estimator included [s].
        stddev: ``(N, 42)`` σ of δM after each sample [mm] (NaN while the IK used no estimate,
            and between the rows :func:`parameter_stride` keeps of an online run), or None
            (``nominal``).
        nis: ``(N,)`` normalised innovation squared of each sample (Kalman methods; NaN where
            refused), or None.
        unloaded: δM is the drive without any load, the sag being the elastic model's (its truth
            is the robot's unloaded drive); False: δM is the drive in force, sag included.
        blocks: the estimator's other unknowns at the end of the run, ``{key: {"names",
            "estimate", "stddev"}}`` in file units (spec §7: ``tracker_geometry``, ``compliance``).
    """

    method: str
    result: SimulationResult
    trace: np.ndarray
    no_load_error: np.ndarray
    rejected: int
    run_time_s: float
    stddev: np.ndarray | None = None
    nis: np.ndarray | None = None
    unloaded: bool = False
    blocks: dict[str, dict] = field(default_factory=dict)


@dataclass(frozen=True)
class Reproduction:
    """Every run of the experiment, keyed by run name (``nominal`` first, then :data:`METHODS`,
    then the online methods part by part: :func:`online_runs`)."""

    experiment: Experiment
    config: EstimatorConfig
    runs: dict[str, MethodRun]
    parts: tuple[Part, ...] = ()
    #: figure files already drawn, PNG by file name: what :func:`reproduce`'s ``draw`` made of each run
    drawn: dict[str, bytes] = field(default_factory=dict)

    @property
    def calibrated(self) -> list[str]:
        """Every run but ``nominal``, in order."""
        return [name for name in self.runs if name != NOMINAL]

    @property
    def online(self) -> list[str]:
        """The online runs, in order."""
        return [name for name in self.calibrated if name != BATCH_METHOD]

    def fullest(self, method: str) -> str:
        """The run of ``method`` with every part of the model."""
        return fullest_run(method, self.parts)

    @property
    def platform(self) -> Platform:
        return self.experiment.platform

    @property
    def stage_names(self) -> list[str]:
        return [stage.name for stage in self.experiment.stages]

    def true_no_load_error(self, run: str = NOMINAL) -> np.ndarray:
        """δM a perfect no-load calibration of ``run``'s model would find [mm]: the true drive at
        home under the platform's own weight, minus nominal; for a run whose model carries the sag
        (:attr:`MethodRun.unloaded`), the robot's unloaded drive minus nominal."""
        robot = self.runs[NOMINAL].result.robot
        if self.runs[run].unloaded:
            return robot.base_params - self.platform.drive.as_vector()
        drive = robot.drive_at(self.platform.required_workspace("the no-load calibration").home, 0.0)
        return drive.as_vector() - self.platform.drive.as_vector()


class _PassedThrough:
    """A controller wrapper the simulator sees through: what the wrapper does not define (the
    drive model, ``adaptive``, any command hook the controller offers) is the wrapped one's."""

    def __init__(self, controller):
        self.controller = controller

    def __getattr__(self, name: str):
        if name == "controller":  # not set yet (copy, pickle): no wrapped controller to ask
            raise AttributeError(name)
        return getattr(self.controller, name)


class _Counted(_PassedThrough):
    """Passes a controller through, ticking the overall progress bar after each sample."""

    def __init__(self, controller, bar):
        super().__init__(controller)
        self._bar = bar

    def observe(self, sample) -> None:
        self.controller.observe(sample)
        self._bar.update()


#: at most this many rows per parameter series kept with σ, recorded and drawn (the paper run:
#: every 4th sample, 0.4 s).
PARAMETER_ROWS_MAX = 1000


def parameter_stride(n_samples: int) -> int:
    """Every how many samples the parameter series keep their σ and are logged (1 for short runs)."""
    return max(1, math.ceil(n_samples / PARAMETER_ROWS_MAX))


class _Diagnosed(_PassedThrough):
    """Passes an :class:`EstimatorController` through, keeping the estimator's σ [mm] after every
    ``every``-th sample (``estimate()``: isam2 pays ~2 ms of marginal for it, the series is drawn
    and recorded at that stride anyway) and, for a Kalman filter, its NIS after each."""

    def __init__(self, controller: EstimatorController, every: int = 1):
        super().__init__(controller)
        self.kalman = isinstance(controller.estimator, KalmanFiltered)
        self.every = every
        self.stddev: list[np.ndarray] = []
        self.nis: list[float] = []

    def observe(self, sample) -> None:
        refused = len(self.controller.rejected)
        self.controller.observe(sample)
        estimator = self.controller.estimator
        stddev = estimator.estimate().stddev if len(self.stddev) % self.every == 0 else None
        self.stddev.append(np.full(self.controller.drive_model().n_params, np.nan) if stddev is None else stddev)
        self.nis.append(estimator.filter.nis if self.kalman and len(self.controller.rejected) == refused else np.nan)


def first_stage_calibration(result: SimulationResult) -> np.ndarray:
    """Sample indices of the first stage's calibration segment (the paper's no-load calibration)."""
    return np.flatnonzero((result.stages == result.stages[0]) & (result.kinds == "calibration"))


def _timed_run(experiment: Experiment, controller, bar) -> tuple[SimulationResult, float]:
    start = time.perf_counter()
    result = run_experiment(experiment, _Counted(controller, bar))
    return result, time.perf_counter() - start


def run_ls(experiment: Experiment, config: EstimatorConfig, nominal: SimulationResult, bar) -> MethodRun:
    """Fit ``ls`` on the nominal run's no-load calibration samples, then run frozen."""
    start = time.perf_counter()
    calibration = first_stage_calibration(nominal)
    estimator = cast(BatchEstimator, make_estimator(BATCH_METHOD, experiment.platform, config))  # ls: batch
    estimate = estimator.fit([nominal.log[k] for k in calibration])
    fit_s = time.perf_counter() - start
    result, run_s = _timed_run(experiment, FrozenController(estimate.drive(experiment.platform)), bar)
    # What the IK used: nominal during the calibration segment, the frozen fit from then on.
    trace = np.tile(estimate.error, (len(result.log), 1))
    trace[: calibration[-1] + 1] = 0.0
    sigma = np.full(estimate.error.shape, np.nan) if estimate.stddev is None else estimate.stddev
    stddev = np.tile(sigma, (len(result.log), 1))
    stddev[: calibration[-1] + 1] = np.nan
    return MethodRun(BATCH_METHOD, result, trace, estimate.error, len(estimator.rejected), fit_s + run_s, stddev)


def run_online(
    experiment: Experiment,
    config: EstimatorConfig,
    method: str,
    bar,
    platform: Platform | None = None,
    sigma_every: int = 1,
) -> MethodRun:
    """One :class:`EstimatorController` with ``method`` through every stage, its estimator and
    IK on ``platform`` (default: the experiment's; the simulated robot is the experiment's), its
    σ kept after every ``sigma_every``-th sample."""
    platform = experiment.platform if platform is None else platform
    controller = EstimatorController(make_estimator(method, platform, config), platform)
    diagnosed = _Diagnosed(controller, sigma_every)
    result, run_s = _timed_run(experiment, diagnosed, bar)
    trace = controller.trace()
    last_of_first_stage = int(np.flatnonzero(result.stages == result.stages[0])[-1])
    nis = np.array(diagnosed.nis) if diagnosed.kalman else None
    return MethodRun(
        method,
        result,
        trace,
        trace[last_of_first_stage],
        len(controller.rejected),
        run_s,
        np.array(diagnosed.stddev),
        nis,
        platform.elastic is not None,
        controller.estimator.estimate().block_results(),
    )


#: ticks a worker process batches before it sends them to the parent's bar (a few a second)
TICKS_PER_MESSAGE = 100


class _QueueBar:
    """A worker's stand-in for the progress bar: counts ticks and sends them to the parent in batches."""

    def __init__(self, queue) -> None:
        self._queue, self._pending = queue, 0

    def update(self, n: int = 1) -> None:
        self._pending += n
        if self._pending >= TICKS_PER_MESSAGE:
            self.flush()

    def flush(self) -> None:
        if self._pending:
            self._queue.put(self._pending)
            self._pending = 0


_worker_queue = None


def _init_worker(queue) -> None:
    global _worker_queue
    _worker_queue = queue


#: what :func:`reproduce` may draw of a run where it ran: ``draw(run name, run)`` → PNG by file name
DrawRun = Callable[[str, MethodRun], dict[str, bytes]]


def _run_and_draw(name: str, task: Callable[..., MethodRun], draw: DrawRun | None, bar) -> tuple[MethodRun, dict]:
    run = task(bar=bar)
    return run, ({} if draw is None else draw(name, run))


def _run_in_worker(name: str, task: Callable[..., MethodRun], draw: DrawRun | None) -> tuple[MethodRun, dict]:
    bar = _QueueBar(_worker_queue)
    try:
        return _run_and_draw(name, task, draw, bar)
    finally:
        bar.flush()


class WorkerPool:
    """Fresh worker processes for :func:`reproduce`'s runs, which a caller that makes the pool may
    hand the work that needs every run afterwards (the comparison figures), while the processes
    are up: a process costs its imports and kernel loads (~2 s) to start."""

    def __init__(self, workers: int) -> None:
        ctx = multiprocessing.get_context("spawn")  # no fork: gtsam's and numba's threads do not survive one
        self.queue = ctx.SimpleQueue()
        self.executor = concurrent.futures.ProcessPoolExecutor(
            workers, ctx, initializer=_init_worker, initargs=(self.queue,)
        )

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.executor.shutdown(cancel_futures=True)


def _in_processes(
    tasks: dict[str, Callable[..., MethodRun]], pool: WorkerPool, bar, draw: DrawRun | None
) -> dict[str, tuple[MethodRun, dict]]:
    """The runs of ``tasks`` in ``pool``'s processes, the longest first (isam2's: online methods'
    runs cost from ~0.1 s to tens of seconds), each drawn by ``draw`` where it ran, ticking
    ``bar`` as they go."""
    order = sorted(tasks, key=lambda name: (name.split("+")[0] != "isam2", -name.count("+")))
    futures = {pool.executor.submit(_run_in_worker, name, tasks[name], draw): name for name in order}
    pending = set(futures)
    while pending:
        _, pending = concurrent.futures.wait(pending, timeout=0.2)
        while not pool.queue.empty():
            bar.update(pool.queue.get())
    while not pool.queue.empty():
        bar.update(pool.queue.get())
    return {futures[future]: future.result() for future in futures}


def reproduce(
    experiment: Experiment,
    config: EstimatorConfig,
    progress: bool = False,
    parts: tuple[Part, ...] = (),
    workers: int | WorkerPool = 1,
    draw: DrawRun | None = None,
) -> Reproduction:
    """Run the experiment before calibration, with every method of :data:`METHODS` on ``config``,
    and with :data:`LAYERED_METHODS` once more per part of ``parts`` (:func:`online_runs`).

    Args:
        progress: bars on stderr when it is a terminal: the run before calibration, then one
            across the methods' runs.
        workers: processes the runs after the one before calibration share (each run is
            independent: same experiment, seed and noise draws; only the controller differs), or
            a :class:`WorkerPool` of them that the caller keeps for more work. 1 runs them in this
            process; more cost each process its imports and kernel loads (~2 s), so they pay off
            on the full experiment. The processes are spawned: a script that calls this with
            ``workers > 1`` needs the ``if __name__ == "__main__":`` guard.
        draw: what to draw of each run as soon as it is done, in the process that ran it (while
            the other runs go on), kept in :attr:`Reproduction.drawn`; picklable where ``workers > 1``.
    """
    start = time.perf_counter()
    nominal_result = run_experiment(experiment, NominalController(experiment.platform), progress=progress)
    n, m = len(nominal_result.log), experiment.platform.drive.n_params
    nominal = MethodRun(NOMINAL, nominal_result, np.zeros((n, m)), np.zeros(m), 0, time.perf_counter() - start)
    # each run a call short of its progress bar (picklable: module-level functions and data)
    tasks: dict[str, Callable[..., MethodRun]] = {BATCH_METHOD: partial(run_ls, experiment, config, nominal_result)}
    for name, method, run_parts in online_runs(parts):
        platform = estimator_platform(experiment, run_parts)
        run_config = run_parts[-1].config if run_parts else config
        tasks[name] = partial(
            run_online, experiment, run_config, method, platform=platform, sigma_every=parameter_stride(n)
        )
    with progress_bar(
        total=n * len(tasks), desc=f"reproduce {experiment.name}: {', '.join(tasks)}", show=progress
    ) as bar:
        if isinstance(workers, WorkerPool):
            done = _in_processes(tasks, workers, bar, draw)
        elif workers > 1:
            with WorkerPool(workers) as pool:
                done = _in_processes(tasks, pool, bar, draw)
        else:
            done = {name: _run_and_draw(name, task, draw, bar) for name, task in tasks.items()}
    runs = {NOMINAL: nominal, **{name: done[name][0] for name in tasks}}
    return Reproduction(
        experiment, config, runs, parts, {file: png for name in tasks for file, png in done[name][1].items()}
    )
