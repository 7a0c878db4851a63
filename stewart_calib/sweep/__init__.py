"""Monte Carlo studies of the estimators at scale, on Dask distributed (spec §9).

``stewart-calib sweep --spec S.toml --out DIR`` (:mod:`stewart_calib.pipelines.sweep`) runs
every cell × seed of a grid (:mod:`.spec`) as an independent task (:mod:`.task`: simulate,
run every method on the same data, score against the truth and the Cramér–Rao bound) on an
embedded local cluster or a named scheduler (:mod:`.runner`), writes rows as tasks finish and
resumes where it stopped (:mod:`.store`), and writes a summary and plots (:mod:`.summary`).

Python::

    from stewart_calib.sweep import load_spec, run_sweep
    report = run_sweep(load_spec("configs/sweeps/smoke.toml"), "out/smoke", workers=2)
"""

from .runner import SweepReport, run_sweep
from .spec import SweepSpec, load_spec

__all__ = ["SweepReport", "SweepSpec", "load_spec", "run_sweep"]
