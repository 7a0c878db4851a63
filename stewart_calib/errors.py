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


def number(value: object) -> str:
    """A number for a message: 15 significant digits, so that a time read as ``7.1`` from a file
    shows as ``7.1``, not the 7.1 and fifteen more digits that arithmetic on it leaves (``repr``'s 17),
    while an epoch time keeps its microseconds; anything else as ``str``."""
    try:
        return f"{float(value):.15g}"  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return str(value)


def did_you_mean(word: str, known) -> str:
    """``" (did you mean 'x'?)"`` naming the known word nearest a misspelt one, or ``""``."""
    import difflib  # only a refusal needs it

    close = difflib.get_close_matches(word, sorted(known), n=1, cutoff=0.5)
    return f" (did you mean '{close[0]}'?)" if close else ""
