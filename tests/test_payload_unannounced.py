"""An unannounced payload on the paper's experiment (spec §10, ``[elastic] payload_sigma_kg``): the
nim-stewart robot with its in-situ tracker, the no-load stage, then 40 kg put on at once, logged without
``load_kg``; the platform declares ``payload_sigma_kg = 50``. ``ekf`` with ``--config paper`` (its fast
δM walk takes most of what the payload does to the legs: a sample sees a step of it by a fraction of
its σ) finds the step only from the samples after it, and ends within 2σ of 40 kg.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from benchmarks.elastic import PAYLOAD_STAGE_KG, paper_payload_experiment, unannounced_payload
from stewart_calib.simulation import run_experiment
from stewart_calib.simulation.load import elastic_of


def test_ekf_with_the_paper_config_finds_an_unannounced_40_kg_step(tmp_path):
    experiment = paper_payload_experiment(tmp_path, seed=1)
    run = run_experiment(experiment)
    assert np.asarray(run.payload_kg)[-1] == PAYLOAD_STAGE_KG
    platform = replace(experiment.platform, elastic=elastic_of(experiment.load))
    found, sigma, steps = unannounced_payload(platform, run.log, "ekf", "paper")
    # before the step was tested by the samples after it: no step taken, 12.2 ± 2.1 kg (13σ off)
    assert steps >= 1 and abs(found - PAYLOAD_STAGE_KG) < 2.0 * sigma, (found, sigma, steps)
