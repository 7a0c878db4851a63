"""The project's error types: messages a user can act on.

Every refusal of a bad file, argument or sample raises :class:`CalibError` with a
single line naming the file, row, column or key and what was expected. The command
line prints that line and exits non-zero; it never shows a traceback for one.
"""


class CalibError(ValueError):
    """A user-facing error: ``str(err)`` is one line naming what is wrong and where."""

    def __reduce__(self):
        # a refusal raised in a worker process (a pool, a Dask worker) is pickled back to the caller;
        # the default re-creates it as ``type(err)(*err.args)``, which fails for the subclasses whose
        # constructor takes more than the message (SampleRejected's reason, SingularStatics' index)
        return _unpickled, (type(self), self.args, self.__dict__)


def _unpickled(cls: type, args: tuple, state: dict) -> CalibError:
    """A pickled :class:`CalibError` made again without its constructor: its message and attributes."""
    err = cls.__new__(cls, *args)
    err.args = args
    err.__dict__.update(state)
    return err


class SampleRejected(CalibError):
    """An estimator refused one sample (NaN, out of range, FK failure, gated outlier).

    The estimator's state is untouched when this is raised; ``str(err)`` says why in words,
    ``err.reason`` in one of the fixed categories below (the summaries count by it).
    """

    NON_FINITE = "non-finite value"
    OUT_OF_RANGE = "out of range"
    FK_FAILED = "FK failed"
    TIME_BACK = "time went back"
    GATED = "gated outlier"
    NOT_POSITIVE_DEFINITE = "innovation covariance not positive definite"
    SOLVER = "solver failed"
    NO_POSE = "measurement fixes no pose"

    #: the refused sample's time [s], set on a late rejection (estimators.base.take_late_rejections)
    t_s: float

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason


def shown(name: object) -> str:
    """``name`` (taken from a file or the command line) safe to put in a one-line message:
    line breaks, control characters (ESC, OSC, BEL, …) and other unprintable characters as
    Python escapes, so no name can forge a line or reach the terminal as a command."""
    return "".join(ch if ch.isprintable() else ascii(ch)[1:-1] for ch in str(name))


#: significant digits of a number in a message or a file: every double reads back from 15 decimal
#: digits as the number they name (DBL_DIG), while ``repr``'s 16th and 17th are mostly the binary
#: noise arithmetic leaves (``0.1 * 7`` is ``0.7000000000000001``, 12° through radians ``12.000000000000002``)
SIGNIFICANT_DIGITS = 15


def number(value: object) -> str:
    """A number for a message: 15 significant digits, so that a time read as ``7.1`` from a file
    shows as ``7.1``, not the 7.1 and fifteen more digits that arithmetic on it leaves (``repr``'s 17),
    while an epoch time keeps its microseconds; anything else as ``str``."""
    try:
        return f"{float(value):.{SIGNIFICANT_DIGITS}g}"  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return str(value)


#: 10**k as doubles, k = 0 … 22: each exact, so a quotient by one is the correctly rounded decimal
_EXACT_POWERS_OF_TEN = [float(10**k) for k in range(23)]


def without_noise(value):
    """``value`` as a file writes it: every float rounded to the number :func:`number` shows (15
    significant digits), so that its ``repr`` holds no binary noise (``0.7``, not ``0.7000000000000001``)
    while keeping every digit a double carries meaningfully (it moves a value by at most half a unit
    in its 15th digit, 5e-15 relative, far below any measurement's noise).

    A float (Python or numpy) gives a float, a float array an array of the same shape, a list, tuple
    or dict the same with its floats rounded (a JSON document); anything else (ints, bools, text) is
    returned as it is, and NaN and ±inf stay what they are. An array is rounded in numpy, to the same
    doubles as ``float(f"{x:.15g}")`` of each element (``tests/test_written_numbers.py`` holds them
    equal): its 15-digit integer ``N = rint(x·10^k)`` is exact but where the product falls on a half,
    decided then by the product's exact remainder (Dekker's two-product), and ``N / 10^k`` is the
    correctly rounded decimal for ``0 ≤ k ≤ 22`` (``1e-8 ≤ |x| < 1e15``); elements outside go through
    Python's formatting.
    """
    import numpy as np  # errors sits below numpy's users; only a writer needs it

    if isinstance(value, float | np.floating):
        return float(f"{value:.{SIGNIFICANT_DIGITS}g}")
    if isinstance(value, np.ndarray):
        return _array_without_noise(value) if value.dtype.kind == "f" else value
    if isinstance(value, dict):
        return {key: without_noise(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(without_noise(item) for item in value)
    return value


def _array_without_noise(values):
    """A float array's :func:`without_noise` (see there)."""
    import numpy as np

    values = np.asarray(values, dtype=float)
    magnitude = np.abs(values)
    scaled = (magnitude >= 1e-8) & (magnitude < 1e15)
    with np.errstate(divide="ignore"):
        digits = SIGNIFICANT_DIGITS - 1 - np.floor(np.log10(np.where(scaled, magnitude, 1.0))).astype(np.intp)
    scale = np.take(_EXACT_POWERS_OF_TEN, np.clip(digits, 0, 22))
    inside = np.where(scaled, values, 0.0)
    product = inside * scale
    whole = np.rint(product)
    half = np.abs(product - whole) == 0.5
    if half.any():  # the product rounded onto a half: the exact remainder says which way its digits go
        remainder = _product_remainder(inside[half], scale[half])
        below = product[half] < whole[half]
        whole[half] += np.where(below, -1.0 * (remainder < 0), 1.0 * (remainder > 0))
    rounded = np.where(scaled, whole / scale, values)
    others = ~scaled & np.isfinite(values) & (values != 0)
    if others.any():
        rounded[others] = [float(f"{x:.{SIGNIFICANT_DIGITS}g}") for x in values[others].tolist()]
    return rounded


def _product_remainder(a, b):
    """``a·b − fl(a·b)`` exactly (Dekker's two-product by Veltkamp's split; no overflow for the
    magnitudes :func:`_array_without_noise` scales)."""

    def split(x):
        big = 134217729.0 * x  # 2^27 + 1
        high = big - (big - x)
        return high, x - high

    product = a * b
    (a_high, a_low), (b_high, b_low) = split(a), split(b)
    return ((a_high * b_high - product) + a_high * b_low + a_low * b_high) + a_low * b_low


def did_you_mean(word: str, known) -> str:
    """``" (did you mean 'x'?)"`` naming the known word nearest a misspelt one, or ``""``."""
    import difflib  # only a refusal needs it

    close = difflib.get_close_matches(word, sorted(known), n=1, cutoff=0.5)
    return f" (did you mean '{close[0]}'?)" if close else ""
