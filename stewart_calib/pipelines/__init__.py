"""What a user runs: one module per ``stewart-calib`` subcommand (``add_parser``, ``main``).

The command line itself (:mod:`stewart_calib.cli`) sits on top and lists the subcommands; the
pieces it shares with each pipeline's ``main(argv)`` live here, so nothing points back up.
"""

import argparse
import importlib
import math
import os
import sys

from ..errors import CalibError, shown
from ..resources import shipped_names


class Parser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line and exit 2, as every other refusal."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


#: ``stewart-calib COMMAND``: the module of this package that implements it, and its line in
#: ``stewart-calib --help``. Listing them needs no import; a run imports its own module only,
#: so no command pays for another's dependencies (rerun, gtsam, the reproduction, …).
COMMANDS = {
    "calibrate": ("calibrate", "identify the 42 drive parameters from a measurement log"),
    "simulate": ("simulate", "simulate an experiment (true robot, load, tracker) and write platform, log and truth"),
    "reproduce": ("reproduce", "reproduce the paper's experiments (Tables 4-6, Figs. 5-9) on the simulated platform"),
    "track": ("track", "calibrate online from a log as it is written (a growing file or standard input)"),
    "identifiability": (
        "identifiability",
        "singular values, predicted parameter std devs and weak directions of a pose set",
    ),
    "plan": ("plan", "choose calibration poses (optimal design over random workspace poses)"),
    "compensate": ("compensate", "strokes for desired poses with the calibrated model (IK of nominal + error)"),
    "import": (
        "import_files",
        "turn a Motive/Vicon/laser-tracker/CSV export and a controller log into a measurement log",
    ),
    "export": ("export", "write the calibrated drive for a controller (LinuxCNC genhexkins, plain JSON)"),
    "import-bag": ("import_bag", "turn a ROS 1 / ROS 2 bag into a measurement log"),
    "validate": ("validate", "predict a held-out log with a calibration and report the errors (spec §7)"),
    "score": ("score", "score a calibration result against a simulation's truth.csv (parameters, z², closed loop)"),
    "sweep": ("sweep", "run a Monte Carlo study of the estimators (grid × seeds) on Dask"),
}


class _Subcommands:
    """The ``add_subparsers`` action as a pipeline's ``add_parser`` sees it: the one-line help
    comes from :data:`COMMANDS`, the arguments from the pipeline."""

    def __init__(self, action):
        self._action = action

    def add_parser(self, name: str, **kwargs) -> argparse.ArgumentParser:
        return self._action.add_parser(name, help=COMMANDS[name][1], **kwargs)


def add_subcommands(parser: argparse.ArgumentParser, load=None) -> None:
    """Register every command of :data:`COMMANDS`: those in ``load`` (default: all) with their
    module's arguments, the others by name and help only (what ``--help`` lists)."""
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for name, (module, help_line) in COMMANDS.items():
        if load is None or name in load:
            importlib.import_module(f".{module}", __name__).add_parser(_Subcommands(sub))
        else:
            sub.add_parser(name, help=help_line, add_help=False)


#: the arguments (``argparse`` dests) that name files a command reads, and those it writes; ``track``'s
#: ``--checkpoint`` is both (it resumes from and replaces the same file).
INPUT_ARGUMENTS = (
    *("platform", "log", "result", "poses", "experiment", "spec", "config", "bag", "checkpoint"),
    *("motive", "vicon", "csv", "point_list", "strokes", "mapping", "truth"),  # import, score
)
OUTPUT_ARGUMENTS = ("out", "trace", "rerun", "platform_out", "json", "checkpoint")
#: outputs that are directories, with the files a command writes in them (those it names before
#: its work; the others, a sweep's plots, are checked as they are written: :func:`io.written_target`)
OUTPUT_DIRECTORIES = {
    ("simulate", "out"): ("platform.toml", "log.csv", "truth.csv"),
    ("sweep", "out"): ("results.parquet", "summary.csv", "summary.md"),
    ("reproduce", "out"): ("results.json", "tables.md", "index.html", "reproduce.rrd"),
    ("*", "report"): ("index.html",),
}


def ini_sibling(path: str | os.PathLike) -> str:
    """The INI file ``export --format linuxcnc --out F`` writes beside ``F``: ``F`` with the suffix ``.ini``."""
    root, _ = os.path.splitext(os.fspath(path))
    return root + ".ini"


#: files a command writes beside an output file, from its arguments
OUTPUT_SIBLINGS = {("export", "out"): lambda args, path: [ini_sibling(path)] if args.format == "linuxcnc" else []}


def _option(dest: str) -> str:
    return "BAG" if dest == "bag" else "--" + dest.replace("_", "-")


def _written_files(args: argparse.Namespace) -> list[tuple[str, str]]:
    """``(option, path)`` of every file the command will write (within output directories too)."""
    written: list[tuple[str, str]] = []
    for dest in OUTPUT_ARGUMENTS:
        value = getattr(args, dest, None)
        if not value or value == "-":
            continue
        files = OUTPUT_DIRECTORIES.get((args.command, dest)) or OUTPUT_DIRECTORIES.get(("*", dest))
        written += [(_option(dest), os.path.join(value, name)) for name in files] if files else [(_option(dest), value)]
        siblings = OUTPUT_SIBLINGS.get((args.command, dest))
        if siblings is not None:
            written += [(_option(dest), sibling) for sibling in siblings(args, value)]
    for (command, dest_name), files in OUTPUT_DIRECTORIES.items():
        value = getattr(args, dest_name, None)
        if command in (args.command, "*") and dest_name not in OUTPUT_ARGUMENTS and value:
            written += [(_option(dest_name), os.path.join(value, name)) for name in files]
    return written


def check_no_output_over_input(args: argparse.Namespace) -> None:
    """Refuse, before any work, an output path that names an input file of the same command
    (the same file, by any path or link) or another of its outputs, or a directory: the write
    would destroy it. The same check is made again by every write (:func:`~stewart_calib.io.written_target`).

    Raises:
        CalibError: naming both arguments and the path.
    """
    written = _written_files(args)
    seen: dict[str, str] = {}
    for option, path in written:
        key = os.path.realpath(path)
        if key in seen and seen[key] != option:
            raise CalibError(f"{option} {shown(path)}: is also the {seen[key]} output; expected another path")
        seen.setdefault(key, option)
    from .. import io

    with io.protected_inputs(_read_files(args)):  # by identity: any name or link of an input
        for option, path in written:
            io.written_target(path, option)


def _read_files(args: argparse.Namespace) -> dict[str, str]:
    """``path → option`` of the files the command reads and does not replace on purpose (every
    write checks it is none of them: :func:`~stewart_calib.io.protected_inputs`)."""
    written = {option for option, _ in _written_files(args)}
    files: dict[str, str] = {}
    for dest in INPUT_ARGUMENTS:
        value = getattr(args, dest, None)
        if isinstance(value, str) and value != "-" and _option(dest) not in written:
            files.setdefault(value, _option(dest))
    return files


def _refuse_special_file(option: str, path: str) -> None:
    """An output that the command reads back (``track``'s checkpoint) must be a file: a device,
    FIFO or socket written through cannot be resumed from."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError:  # not there yet (or unreachable: the directory's check says why)
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
        raise CalibError(
            f"{option} {shown(path)}: is {kind}, not a regular file; it is read back on a resume — expected a file path"
        )


def check_outputs_writable(args: argparse.Namespace) -> None:
    """Refuse, before any work, an output whose directory cannot be written into — the one it is
    in, or for one still to be made the nearest that exists (:func:`~stewart_calib.io.check_writable_directory`):
    every command, so none finds out only when it writes its result —, an output file that is a
    directory, and one the command reads back that is a device, FIFO or socket. Any other device,
    FIFO or descriptor (``/dev/stdout``) is written through (:func:`~stewart_calib.io.written_target`).

    Raises:
        CalibError: naming the argument, the directory and the file system's reason.
    """
    from .. import io

    for option, path in _written_files(args):
        if option in map(_option, INPUT_ARGUMENTS):
            _refuse_special_file(option, path)
        if io.written_target(path, option).through:
            continue
        directory = os.path.abspath(path)
        if not os.path.isdir(directory):  # an output directory (sweep, reproduce) that exists: itself
            directory = os.path.dirname(directory)
            while not os.path.isdir(directory) and directory != os.path.dirname(directory):
                directory = os.path.dirname(directory)
        io.check_writable_directory(directory, f"{option} {shown(path)}")


#: optional dependencies (top-level module → the extra of pyproject.toml that installs it)
OPTIONAL_EXTRAS = {"rosbags": "ros"}


def dispatch(args: argparse.Namespace) -> int:
    """Run the parsed subcommand: a :class:`CalibError` becomes one line on stderr and exit 2, and
    so does a missing optional dependency (naming the extra that installs it)."""
    from .. import io

    try:
        check_no_output_over_input(args)
        check_outputs_writable(args)
        with io.protected_inputs(_read_files(args)):
            return int(args.func(args) or 0)
    except CalibError as refusal:  # names from files may hold line breaks or terminal escapes: shown escaped
        err = _located(refusal, args)
        print(f"stewart-calib {args.command}: error: {shown(err)}", file=sys.stderr)
        return 2
    except OSError as err:  # the file system's refusals no check could foresee: full, read-only, I/O
        where = f"{shown(err.filename)}: " if err.filename else ""
        print(f"stewart-calib {args.command}: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"stewart-calib {args.command}: error: out of memory", file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        extra = OPTIONAL_EXTRAS.get((err.name or "").split(".")[0])
        if extra is None:
            raise
        print(
            f"stewart-calib {args.command}: error: needs the optional package '{err.name}': "
            f"pip install 'stewart-calib[{extra}]'",
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print(f"stewart-calib {args.command}: interrupted", file=sys.stderr)
        return 130


def _located(err: CalibError, args: argparse.Namespace) -> CalibError:
    """A singular-statics refusal (spec §10) naming the row of the log or pose list it came from."""
    from ..model.statics import SingularStatics

    platform = getattr(args, "platform", None)
    log, poses = getattr(args, "log", None), getattr(args, "poses", None)
    path = log or poses
    if not isinstance(err, SingularStatics) or platform is None or not path:
        return err
    from .handover import singular_statics_row

    return singular_statics_row(err, platform, str(path), bool(log), bool(getattr(args, "skip_bad_rows", False)))


def check_output_path(path, option: str) -> None:
    """Fail before a long run, not after it, when an output cannot be placed (``path`` None: no
    such output asked for)."""
    if path is not None:
        from .. import io

        io.check_writable_directory(path.parent, f"{option} {shown(path)}")


def add_config_arguments(parser: argparse.ArgumentParser, example: str = "isam2.lag_s=5") -> None:
    """``--config C.toml`` and repeatable ``--set section.key=value`` (see ``load_estimator_config``)."""
    parser.add_argument(
        "--config",
        metavar="C.toml",
        help=f"estimator config: a file or a shipped name ({', '.join(shipped_names('estimators'))}); "
        "default: default.toml values",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help=f"override a config value, e.g. {example}",
    )


def positive_number(text: str, what: str = "number") -> float:
    """An option's value that must be a finite positive number (an argparse ``type``; ``what``
    names it in the refusal, e.g. ``"number of seconds"``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite positive {what}, got {text!r}")
    return value


def add_tolerance_arguments(parser: argparse.ArgumentParser) -> None:
    """``--tolerance-mm``, ``--tolerance-deg`` and ``--fail-over-tolerance``: what the verdict line
    (:func:`~stewart_calib.analysis.accuracy.verdict_line`) compares the expected errors with."""
    parser.add_argument(
        "--tolerance-mm", type=positive_number, metavar="MM", help="position error the robot must keep to (verdict)"
    )
    parser.add_argument(
        "--tolerance-deg", type=positive_number, metavar="DEG", help="orientation error to keep to (verdict)"
    )
    parser.add_argument(
        "--fail-over-tolerance",
        action="store_true",
        help="exit 1 when the verdict is over the tolerance or not surely within it (outputs are written)",
    )


def run_command(name: str, argv: list[str] | None = None) -> int:
    """Run ``stewart-calib NAME ARGV…`` (``argv`` None: this process's arguments): each pipeline's ``main``."""
    parser = Parser(prog="stewart-calib")
    add_subcommands(parser, [name])
    return dispatch(parser.parse_args([name, *(sys.argv[1:] if argv is None else argv)]))
