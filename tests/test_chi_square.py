"""stewart_calib.chi_square, the χ² quantile of the filters' gates without scipy.special's import,
against scipy.special.chdtri itself."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import chdtri as scipy_chdtri
from scipy.special import gammainc, gammaincc

from stewart_calib.chi_square import chdtri, regularised_gamma

DOFS = (0.5, 0.51, 0.7, 1.0, 1.5, 2.0, 3.0, 5.3, 6.0, 12.0, 18.0, 42.0, 100.0, 300.5, 1000.0, 1e4)
#: 1 − p of every gate probability p a float can hold below 1, to the median and the lower tail
TAILS = (1.1e-16, 1e-12, 1e-6, 1e-3, 0.0027, 0.01, 0.05, 0.3, 0.5, 0.7, 0.9, 0.999, 1 - 1e-9)


def test_regularised_gamma_is_scipys():
    for a in np.array(DOFS) / 2:
        for x in (1e-3, 0.5 * a, a, a + 1.0, 2.0 * a + 5.0, 5.0 * a + 30.0):
            P, Q = regularised_gamma(a, x)
            # the one computed (P below x = a + 1, Q above) carries the rounding of the exponent
            # a·ln x − x − ln Γ(a) of its factor (relative error ~ its size × ε); the other is its
            # complement, off by as much in absolute terms (so is scipy's: its Q(½, ½) is 10 ulps off erfc(√½))
            exponent = a * abs(np.log(x)) + x + abs(math.lgamma(a))
            rtol = 8 * np.finfo(float).eps * (exponent + 1.0)
            (computed, expected), (complement, expected_complement) = (
                ((P, gammainc(a, x)), (Q, gammaincc(a, x)))
                if x < a + 1
                else ((Q, gammaincc(a, x)), (P, gammainc(a, x)))
            )
            assert computed == pytest.approx(expected, rel=rtol)
            assert complement == pytest.approx(expected_complement, abs=rtol)


def test_quantile_is_scipys():
    for dof in DOFS:
        for tail in TAILS:
            assert chdtri(dof, tail) == pytest.approx(scipy_chdtri(dof, tail), rel=1e-13), (dof, tail)


def test_quantile_refuses_what_has_none():
    for dof, tail in ((0.0, 0.5), (-1.0, 0.5), (6.0, 0.0), (6.0, 1.0), (float("nan"), 0.5), (6.0, float("nan"))):
        with pytest.raises(ValueError, match="chdtri: expected dof > 0 and 0 < tail < 1"):
            chdtri(dof, tail)
