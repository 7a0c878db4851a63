"""The reproduction's figures as a reader holds them beside the paper's (stewart_calib.reproduction.figures)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from stewart_calib.reproduction.figures import _line_style, _style
from stewart_calib.reproduction.runs import BATCH_METHOD, NOMINAL, Part, Reproduction, online_runs


def _reproduction(n_parts: int) -> Reproduction:
    """A reproduction's runs in the order reproduce() makes them (nominal, ls, then online_runs),
    each standing for a MethodRun by its method alone: all the styles read."""
    parts = tuple(Part(f"part{k}", "", None, "") for k in range(n_parts))
    names = [(NOMINAL, NOMINAL), (BATCH_METHOD, BATCH_METHOD)]
    names += [(run, method) for run, method, _ in online_runs(parts)]
    runs = {run: SimpleNamespace(method=method) for run, method in names}
    return Reproduction(experiment=None, config=None, runs=runs, parts=parts)


@pytest.mark.parametrize("n_parts", [0, 1, 2, 3])
def test_every_run_of_figs_7_to_9_has_a_style_of_its_own(n_parts):
    """ekf and ekf+tracker were both dashed blue, isam2 and isam2+tracker both dashed green."""
    reproduction = _reproduction(n_parts)
    styles = {run: _style(reproduction, run) for run in reproduction.runs}
    seen = [(style["color"], style["linestyle"]) for style in styles.values()]
    assert len(set(seen)) == len(seen), seen
    assert len({(s["color"], s["marker"]) for s in styles.values()}) == len(seen)
    assert {style["label"] for style in styles.values()} == set(reproduction.runs)
    # the fullest run of each estimator, and every run without layers, is drawn solid
    for run, style in styles.items():
        method = reproduction.runs[run].method
        fullest = [name for name in reproduction.runs if reproduction.runs[name].method == method][-1]
        assert (style["linestyle"] == "-") == (run == fullest), run
    assert all("marker" not in _line_style(reproduction, run) for run in reproduction.runs)
