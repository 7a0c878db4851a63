"""The χ² quantile the filters gate with, without importing ``scipy.special``.

``scipy.special`` costs ~0.2 s of every command's start (it pulls in scipy's array-API layer,
``numpy.testing`` and ``numpy.f2py``), a fifth of a command's start-up budget, for one
function called a few times a run. The regularised incomplete gamma function is a short series
or continued fraction (Numerical Recipes §6.2); its inverse a safeguarded Newton iteration.
Agrees with ``scipy.special.chdtri`` to ~1e-13 relative (tests/test_chi_square.py).
"""

from __future__ import annotations

import functools
import math

_EPS = 2.0**-53
_TINY = 1e-300


def regularised_gamma(a: float, x: float) -> tuple[float, float]:
    """``(P(a, x), Q(a, x))``, ``Q = Γ(a, x) / Γ(a) = 1 − P``, for ``a > 0``, ``x ≥ 0``: below
    ``x = a + 1`` the series of P, above it Lentz's continued fraction of Q (each converges fast
    on its side); the other one is its complement."""
    if x <= 0.0:
        return 0.0, 1.0
    scale = math.exp(a * math.log(x) - x - math.lgamma(a))
    if x < a + 1.0:
        term = total = 1.0 / a
        n = a
        while abs(term) > abs(total) * _EPS:
            n += 1.0
            term *= x / n
            total += term
        return total * scale, 1.0 - total * scale
    b = x + 1.0 - a
    c, d = 1.0 / _TINY, 1.0 / b
    fraction = d
    i = 1
    while True:
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = b + an / c
        c = c if abs(c) > _TINY else _TINY
        fraction *= d * c
        if abs(d * c - 1.0) <= _EPS:
            return 1.0 - scale * fraction, scale * fraction
        i += 1


# the robust filter's walk test asks for the same two quantiles at every noise window (~10⁴ Newton
# steps of the series an hour of a 10 Hz log): kept once computed
@functools.lru_cache(maxsize=64)
def chdtri(dof: float, tail: float) -> float:
    """``x`` with ``P(χ²_dof > x) = tail`` (``scipy.special.chdtri``; ``chi2.ppf(p, dof)`` is
    ``chdtri(dof, 1 − p)``) for ``dof > 0``, ``0 < tail < 1``.

    Newton on ``Q(dof/2, x/2) = tail`` from the mean — on ``P = 1 − tail`` for a tail above ½
    (then exact, and P accurate where Q is near 1) — kept inside a bracket that every step
    narrows (bisection where Newton would leave it), to a few ulps of x.

    Raises:
        ValueError: ``dof`` or ``tail`` outside their ranges.
    """
    if not (dof > 0.0 and 0.0 < tail < 1.0):
        raise ValueError(f"chdtri: expected dof > 0 and 0 < tail < 1, got dof={dof!r}, tail={tail!r}")
    a, upper = 0.5 * dof, tail <= 0.5
    target = tail if upper else 1.0 - tail

    def excess(x: float) -> float:
        """``Q(a, x) − tail``, from whichever of P and Q is accurate; decreasing in x."""
        lower_part, upper_part = regularised_gamma(a, x)
        return upper_part - target if upper else target - lower_part

    lo, hi = 0.0, max(a, 1.0)
    while excess(hi) > 0.0:
        lo, hi = hi, 2.0 * hi
    x = min(max(a, lo), hi)
    log_gamma = math.lgamma(a)
    for _ in range(200):
        r = excess(x)
        if r > 0.0:
            lo = x
        else:
            hi = x
        density = math.exp((a - 1.0) * math.log(x) - x - log_gamma) if x > 0.0 else 0.0
        guess = x + r / density if density > 0.0 else math.inf
        if not lo < guess < hi:
            guess = 0.5 * (lo + hi)
        if abs(guess - x) <= 4.0 * _EPS * x or hi - lo <= 4.0 * _EPS * hi:
            return 2.0 * guess
        x = guess
    return 2.0 * x
