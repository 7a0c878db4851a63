"""The project's refusals survive the trip from a worker process back to the caller."""

from __future__ import annotations

import pickle

import pytest

from stewart_calib.errors import CalibError, SampleRejected
from stewart_calib.model.statics import SingularStatics


def _rejected() -> SampleRejected:
    err = SampleRejected("ekf: sample at t = 2792.3 s gated: NIS 31.5 > χ² bound 27.9", SampleRejected.GATED)
    err.t_s = 2792.3  # set on a late rejection
    return err


@pytest.mark.parametrize(
    "err",
    [CalibError("log.csv: row 3: column 's2_mm': expected a number"), _rejected(), SingularStatics("pose 1", 4, 0.5)],
    ids=["CalibError", "SampleRejected", "SingularStatics"],
)
def test_a_refusal_pickles_with_its_message_and_attributes(err):
    # a process pool or a Dask worker hands a raised refusal back pickled; SampleRejected's default
    # unpickling called SampleRejected(message) and broke the pool instead of reporting the refusal
    back = pickle.loads(pickle.dumps(err))  # noqa: S301  # our own bytes, just made
    assert type(back) is type(err)
    assert str(back) == str(err)
    assert back.__dict__ == err.__dict__
