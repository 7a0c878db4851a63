"""What the noise alone leaves in ``validate``'s errors (workflows.validation.noise_squares), drawn.

Held-out logs of a robot that is exactly its model, read by noisy instruments: the mean and the spread
of validate's mean squared errors over many draws against the first-order statistics the verdict
takes the noise out with; then a robot off its model, whose own RMS the stated 90 % interval covers.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.instruments import outside_model
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.samples import Log
from stewart_calib.simulation.instrument import SimulatedInstrument
from stewart_calib.workflows.validation import noise_squares, nominal_model, validate
from tests.instrument_data import HOBBY, hobby, workspace_poses
from tests.test_instrument_ls import POINTS

DRAWS = 400
ROWS = 30
READING_SIGMA_MM, STROKE_SIGMA_MM = 0.002, 0.001


def _outside(kind: str):
    platform = hobby() if kind == "pose" else hobby(POINTS)
    rng = np.random.default_rng(7)
    R, t = kin.pose_to_rt(workspace_poses(platform, ROWS, rng))
    strokes = kin.inverse_kinematics(platform.drive, R, t)
    instrument = SimulatedInstrument(platform.instrument, outside_model(platform).nominal_unknowns(), 0.0)
    return platform, R, t, strokes, instrument, rng


def _mean_squares(platform, logs, register: bool) -> np.ndarray:
    result = nominal_model(platform)
    rows = [validate(platform, result, log, register)[1:] for log in logs]
    position = np.array([np.mean(p**2) for p, _ in rows])
    orientation = None if rows[0][1] is None else np.array([np.mean(o**2) for _, o in rows])
    return position, orientation


def _check(stated, drawn: np.ndarray) -> None:
    """The drawn mean squares' mean within 4 of its standard errors of the stated mean, and their
    variance within 30 % of the stated (a variance of 400 draws is within 7 % of its own, 1σ)."""
    spread = np.sqrt(stated.variance)
    assert abs(np.mean(drawn) - stated.mean) < 4.0 * spread / np.sqrt(DRAWS), (np.mean(drawn), stated.mean)
    assert np.var(drawn) == pytest.approx(stated.variance, rel=0.3)


@pytest.mark.parametrize("kind", ["pose", "points"])
@pytest.mark.parametrize("register", [False, True])
def test_an_outside_instruments_noise_in_validates_errors(kind, register):
    """With the frame fitted again (--register-instrument) the fit absorbs 6 of the noise's 3N (pose:
    6N) degrees of freedom, and validate's mean square is below the 3σ² a reading holds: the statistics
    follow it as the fit's hat matrix shares the 6 out between the rows and the components."""
    platform, R, t, strokes, instrument, rng = _outside(kind)
    logs = [
        Log(np.arange(ROWS) * 0.1, strokes, instrument.read(R, t, instrument.draw(ROWS, rng))) for _ in range(DRAWS)
    ]
    position, orientation = _mean_squares(platform, logs, register)
    stated = noise_squares(platform, nominal_model(platform), logs[0], register, ROWS, 0.0, 0.0)
    _check(stated[0], position)
    sigma = platform.instrument.position_sigma_mm
    if register and kind == "points":  # every target seen: the 6 come off the 3 K N equal components alike
        K = platform.instrument.n_targets
        assert stated[0].mean == pytest.approx(3 * sigma**2 * (1 - 6 / (3 * K * ROWS)), rel=1e-9)
    elif register:  # the frame's translation off the positions alone, its rotation shared with the angles
        assert 3 * sigma**2 * (1 - 6 / (3 * ROWS)) <= stated[0].mean <= 3 * sigma**2 * (1 - 3 / (3 * ROWS))
    else:
        assert stated[0].mean == pytest.approx(3 * sigma**2, rel=1e-12)
    if kind == "pose":
        _check(stated[1], orientation)
    else:
        assert orientation is None and stated[1] is None


def test_the_trackers_noise_in_validates_errors():
    """The in-situ tracker: its forward kinematics of noisy readings against the drive's of noisy
    strokes, each row's pose noise ``σ² (JᵀJ)⁻¹`` of both."""
    platform = load_platform(HOBBY.parent / "nim-stewart.toml")
    rng = np.random.default_rng(3)
    R, t = kin.pose_to_rt(workspace_poses(platform, ROWS, rng))
    readings = kin.inverse_kinematics(platform.tracker, R, t)
    strokes = kin.inverse_kinematics(platform.drive, R, t)
    logs = [
        Log(
            np.arange(ROWS) * 0.1,
            strokes + rng.normal(0.0, STROKE_SIGMA_MM, strokes.shape),
            readings + rng.normal(0.0, READING_SIGMA_MM, readings.shape),
        )
        for _ in range(DRAWS)
    ]
    position, orientation = _mean_squares(platform, logs, False)
    stated = noise_squares(platform, nominal_model(platform), logs[0], False, ROWS, READING_SIGMA_MM, STROKE_SIGMA_MM)
    _check(stated[0], position)
    _check(stated[1], orientation)


def test_the_stated_interval_covers_the_robots_own_error():
    """A robot off its model by about as much as the noise leaves (joints and legs σ 0.6 mm off, motion
    capture of σ 0.2 mm, the frame fitted again): the robot's own RMS — its noise-free readings' after
    the same registration — lies in the 90 % interval validate states in 90 % of draws (400 draws: ±4.5 %
    is 3σ of the share)."""
    platform, R, t, _, instrument, rng = _outside("pose")
    true_drive = platform.drive.perturbed(np.random.default_rng(11).normal(0.0, 0.6, 42))
    strokes = kin.inverse_kinematics(true_drive, R, t)
    result = nominal_model(platform)
    clean = Log(np.arange(ROWS) * 0.1, strokes, instrument.read(R, t, np.zeros_like(instrument.draw(ROWS, rng))))
    own = np.sqrt(np.mean(validate(platform, result, clean, True)[1] ** 2))
    stated = noise_squares(platform, result, clean, True, ROWS, 0.0, 0.0)[0]
    assert 0.5 * stated.rms < own < 2.0 * stated.rms  # the noise and the robot's own error both count
    covered = 0
    for _ in range(DRAWS):
        log = replace(clean, readings=instrument.read(R, t, instrument.draw(ROWS, rng)))
        low, high = stated.beyond(np.sqrt(np.mean(validate(platform, result, log, True)[1] ** 2)), 0.9)[1]
        covered += low <= own <= high
    assert 0.855 <= covered / DRAWS <= 0.945, covered


def test_an_error_below_the_noise_is_bounded_by_what_the_noise_can_hide_not_called_zero():
    """The README's hobby log with --register-instrument: orientation RMS 0.0771° where the noise alone
    leaves 0.0859°. The stated interval was "0° (90%: 0–0°)" — the robot surely perfect — because the
    measurement fell below the noise's mean by more than its spread; a measurement the noise happened
    to lower says nothing smaller of the robot than one at the noise's own RMS: the interval's top is
    what the noise's spread lets a robot of no error of its own hide, and it never falls as the
    measured RMS falls."""
    from stewart_calib.workflows.validation import NoiseSquares

    noise = NoiseSquares(0.0859**2, (0.0359**2 / 1.645) ** 2, 4.0 * 0.0859**2 / 60)
    own, (low, high) = noise.beyond(0.0771, 0.9)
    assert own == 0.0 and low == 0.0
    assert high == pytest.approx(0.0359, rel=0.01)
    assert high == noise.beyond(noise.rms, 0.9)[1][1]  # as measured at the noise's own RMS
    tops = [noise.beyond(rms, 0.9)[1][1] for rms in np.linspace(0.0, 0.12, 25)]
    assert all(np.diff(tops) >= 0.0), tops
