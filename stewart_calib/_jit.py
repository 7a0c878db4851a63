"""``njit``: numba's decorator, compiled ahead of time at installation where it can be, with an
on-disk cache wherever one can be written, and numba imported only when a kernel must compile.

**Ahead of time.** A kernel that Python calls (an *entry point*) declares the arguments
its Python callers pass, ``@njit(entry=(F8_1, LEGS, FLOAT, …))`` in the types below. Installing the
package (``setup.py``) compiles every entry point at those types with numba's ``pycc`` into one
extension module, ``stewart_calib._aot_kernels``, with a manifest (:data:`AOT_MANIFEST`) of the
kernel modules' source digests and the processor. A call whose arguments match the declaration runs that machine code:
no compile, no on-disk cache to load, no numba import. Anything else — the module absent (a build
without a compiler), stale (a kernel module edited since, as in an editable install), a call with
other types (tests, a float32 array, a non-contiguous slice), keywords, a kernel called only from
other kernels — takes numba's JIT path below, unchanged. pycc's wrapper checks only an array's item
size, never its dtype, dimensions, layout or writability, and indexing with the wrong ones reads or
writes out of bounds: :meth:`Kernel.__call__` checks each argument against the declaration first
(one function generated per declaration, :func:`argument_check`), and a mismatch goes to the JIT,
which types it.

**JIT.** numba looks for a cache directory when a ``cache=True`` function is *decorated* (here: when
:class:`Kernel` first needs its dispatcher), and raises ``RuntimeError: cannot cache function …``
when neither ``NUMBA_CACHE_DIR``, the ``__pycache__`` beside the source (read-only site-packages)
nor the user-wide cache (read-only home) can be written. :func:`njit` then points numba at a private
directory in the system's temporary directory, and when that cannot be made either, compiles
without a cache (each process pays the compile, a few seconds, instead of failing). A cached kernel's
key holds every kernel module's source (:func:`_keyed_on_kernel_sources`), since its machine code holds
the kernels it calls from other modules.

A JIT compile says so once on a terminal (:class:`CompileNotice`), so the wait is not taken for a
hang. The rules every kernel follows to keep the compile small (together they halve the CPU time and
cut the peak memory of a first ``calibrate --method ekf`` with an empty cache by 30 %):

* every kernel goes through :func:`njit` (never ``numba.njit``): the cache fallbacks above, the
  notice, the AOT build, and LLVM level ``opt`` (:data:`OPT_LEVEL` = 1; :class:`OptimisationLevel`),
  which compiles in ~3/4 of level 3's time and runs as fast (ekf, track, validate, identifiability,
  compensate, isam2). Ask for ``opt=3`` only where a benchmark shows the kernel faster;
* no array-to-array slice assignment (``a[:] = b``, ``a[k, :] = b[j]``) in a kernel: numba compiles
  a formatted shape-mismatch message into each (string joins, ``str`` of ints: ~40 % of a kernel's
  compile). Copy element by element (``_kernels.copy_pose`` for a pose); filling with a
  scalar (``a[:] = 0.0``) is free. Likewise ``@``, ``np.dot`` and ``np.sum`` on the small arrays
  of a kernel compile BLAS glue (~1 s each): write the loop;
* one specialisation per kernel: numba compiles a kernel, and every kernel it calls, once per
  distinct argument type — C or A layout, int32 or int64, a writable or a read-only array, a
  literal or a variable. Python wrappers pass C-contiguous float64 arrays, Python floats and ints,
  and drive or tracker geometry read-only, as :class:`~stewart_calib.model.platform.LegGeometry` holds it
  (the ``entry`` declaration says which); inside a kernel, a constant ``True``/``False`` or integer
  handed to another kernel is a ``Literal`` type of its own (``np.bool_(False)`` is not);
* every kernel called from Python is a compile of its own of its whole call tree (numba links and
  optimises the callees' code into each): add an entry point only where the Python side needs one.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import os
import stat
import sys
import tempfile
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

#: LLVM optimisation level of the kernels (:class:`OptimisationLevel`): level 1 instead of numba's 3
#: compiles in ~3/4 of the time, and the kernels run as fast (the module docstring).
OPT_LEVEL = 1

#: the modules that define kernels: the AOT build imports them, and its manifest holds their digests
KERNEL_MODULES = (
    "stewart_calib.model._kernels",
    "stewart_calib.model.statics",
    "stewart_calib.factors._kernels",
    "stewart_calib.estimators.kalman",
    "stewart_calib.estimators.robust",
    "stewart_calib.simulation.load",
)
#: the extension module the installation builds (setup.py), and its manifest beside it
AOT_MODULE = "stewart_calib._aot_kernels"
#: the AOT module's function that returns its manifest (JSON: entries, kernel source digests, processor)
AOT_MANIFEST = "manifest"
PACKAGE_DIR = Path(__file__).resolve().parent
#: the processor the AOT build compiles for: ``"host"``, this machine's, or ``""``, the architecture's generic one
AOT_TARGET_CPU = "host"


# ----------------------------------------------------------------------------- argument types


@dataclass(frozen=True)
class Array:
    """A numpy array argument of ``ndim`` dimensions and ``dtype`` (float64, int64, bool), C-contiguous
    (``layout="F"``: Fortran, as GTSAM hands its Jacobians) and aligned, as numba types it. ``readonly``:
    the kernel only reads it, so a read-only array is accepted (a writable one too: the AOT code never
    writes it; the JIT would compile a second specialisation)."""

    ndim: int
    dtype: str = "float64"
    readonly: bool = False
    layout: Literal["C", "F"] = "C"
    _flags: tuple[int, int] = field(init=False, repr=False, compare=False)
    _dtype: np.dtype = field(init=False, repr=False, compare=False)

    def numba_type(self):
        from numba import types

        return types.Array(
            getattr(types, "boolean" if self.dtype == "bool" else self.dtype),
            self.ndim,
            self.layout,
            readonly=self.readonly,
        )

    def __post_init__(self) -> None:
        # numpy's flag bits: which to look at and what they must be, for one test of ``flags.num``
        layout = _C_CONTIGUOUS if self.layout == "C" else _F_CONTIGUOUS
        writable = 0 if self.readonly else _WRITEABLE
        object.__setattr__(self, "_flags", (layout | _C_CONTIGUOUS | _ALIGNED | writable, layout | _ALIGNED | writable))
        object.__setattr__(self, "_dtype", np.dtype(self.dtype))

    def accepts(self, value) -> bool:
        return argument_check((self,))(value)

    def check_lines(self, name: str, constants: dict) -> list[str]:
        """Lines of a generated check (:func:`argument_check`) that return False unless ``name`` is such an array."""
        dtype = f"_dtype{len(constants)}"
        constants[dtype] = self._dtype
        mask, wanted = self._flags
        return [
            f"if type({name}) is not ndarray or {name}.ndim != {self.ndim}: return False",
            # numpy's own float64 most often; an equal one (unpickled, read from a file) also
            f"if {name}.dtype is not {dtype} and {name}.dtype != {dtype}: return False",
            f"if {name}.flags.num & {mask} != {wanted}: return False",
        ]


#: numpy's flag bits (``ndarray.flags.num``; numpy/ndarraytypes.h)
_C_CONTIGUOUS, _F_CONTIGUOUS, _ALIGNED, _WRITEABLE = 0x1, 0x2, 0x100, 0x400


@dataclass(frozen=True)
class Scalar:
    """A Python ``float``, ``int`` or ``bool`` argument (or numpy's float64, int64, bool_), as numba types them."""

    kind: str

    def numba_type(self):
        from numba import types

        return {"float": types.float64, "int": types.int64, "bool": types.boolean}[self.kind]

    def accepts(self, value) -> bool:
        return argument_check((self,))(value)

    def check_lines(self, name: str, constants: dict) -> list[str]:
        """As :meth:`Array.check_lines`."""
        types = f"_types{len(constants)}"
        constants[types] = _SCALAR_TYPES[self.kind]
        return [f"if type({name}) not in {types}: return False"]


_SCALAR_TYPES = {"float": (float, np.float64), "int": (int, np.int64), "bool": (bool, np.bool_)}


@dataclass(frozen=True)
class Tuple:
    """A tuple argument of these items."""

    items: tuple

    def numba_type(self):
        from numba import types

        return types.BaseTuple.from_types([item.numba_type() for item in self.items])

    def accepts(self, value) -> bool:
        return argument_check((self,))(value)

    def check_lines(self, name: str, constants: dict) -> list[str]:
        """As :meth:`Array.check_lines`: the tuple's length, then each item, unpacked."""
        names = [f"{name}_{i}" for i in range(len(self.items))]
        lines = [f"if type({name}) is not tuple or len({name}) != {len(names)}: return False"]
        if names:
            lines.append(f"{', '.join(names)}, = {name}")
        for item, item_name in zip(self.items, names, strict=True):
            lines += item.check_lines(item_name, constants)
        return lines


@functools.cache
def argument_check(specs: tuple):
    """A function of ``len(specs)`` arguments that is True when each matches its spec (:class:`Array`,
    :class:`Scalar`, :class:`Tuple`): one flat function generated per declaration, since checking
    spec by spec through method calls and nested tuples costs ~1 µs an array — 15–25 µs a call of
    the filter's kernels, which closed-loop runs and factor graphs call once or more a sample."""
    constants: dict = {"ndarray": np.ndarray}
    names = [f"a{i}" for i in range(len(specs))]
    lines = [line for spec, name in zip(specs, names, strict=True) for line in spec.check_lines(name, constants)]
    source = f"def check({', '.join(names)}):\n" + "".join(f"    {line}\n" for line in [*lines, "return True"])
    # the source holds only names and numbers made above from the declarations, never a user's input
    exec(compile(source, f"<argument check of {len(specs)} arguments>", "exec"), constants)  # noqa: S102
    return constants["check"]


FLOAT, INT, BOOL = Scalar("float"), Scalar("int"), Scalar("bool")
F8_1, F8_2, F8_3 = Array(1), Array(2), Array(3)
I8_1, I8_2, B_1 = Array(1, "int64"), Array(2, "int64"), Array(1, "bool")
#: a Fortran-ordered float64 matrix: the Jacobian blocks GTSAM hands a custom factor
F8_2F = Array(2, layout="F")
#: read-only float64 arrays, as :class:`~stewart_calib.model.platform.LegGeometry` holds them
RO_1, RO_2, RO_3 = (Array(n, readonly=True) for n in (1, 2, 3))
#: a leg set's ``(base joints, platform joints, initial lengths)``, read-only (LegGeometry)
LEGS = Tuple((RO_2, RO_2, RO_1))


# ----------------------------------------------------------------------------- kernels


class Kernel:
    """A kernel: its AOT function (an entry point whose arguments match its declaration) or numba's
    dispatcher, made on first need. numba sees it as that dispatcher (``_numba_type_``), so kernels call
    each other as numba's do; attributes it does not have (``signatures``, …) are the dispatcher's."""

    def __init__(self, py_func, opt: int, options: dict, entry: tuple | None):
        functools.update_wrapper(self, py_func)
        self.py_func, self.opt, self.options, self.entry = py_func, opt, options, entry
        self._dispatcher = None
        self._aot: Any = _UNRESOLVED
        self._check: Callable[..., bool] = argument_check(() if entry is None else entry)

    @property
    def name(self) -> str:
        """``module.qualname``, the key of :data:`ENTRY_POINTS`."""
        return f"{self.py_func.__module__}.{self.py_func.__qualname__}"

    @property
    def dispatcher(self):
        if self._dispatcher is None:
            self._dispatcher = _cached_njit(self.py_func, self.options)
            OPTIMISATION_LEVEL.levels[self._dispatcher] = self.opt
        return self._dispatcher

    @property
    def _numba_type_(self):
        from numba import types

        return types.Dispatcher(self.dispatcher)

    def __call__(self, *args, **kwargs):
        aot = self._aot
        if aot is _UNRESOLVED:
            aot = self._aot = aot_functions().get(self.name) if self.entry is not None else None
        entry = self.entry
        if aot is not None and entry is not None and not kwargs and len(args) == len(entry) and self._check(*args):
            return aot(args)
        return self.dispatcher(*args, **kwargs)

    def __getattr__(self, name: str):
        if name.startswith("__"):  # copy, pickle and friends probe for these: not the dispatcher's
            raise AttributeError(name)
        return getattr(self.dispatcher, name)

    def __reduce__(self):
        return _kernel, (self.py_func.__module__, self.py_func.__qualname__)

    def __repr__(self) -> str:
        return f"<kernel {self.name}>"


def _kernel(module: str, qualname: str) -> Kernel:
    return getattr(importlib.import_module(module), qualname)


_UNRESOLVED = object()

#: every entry point (``njit(entry=…)``) by :attr:`Kernel.name`, in the order their modules defined them
ENTRY_POINTS: dict[str, Kernel] = {}


def njit(opt: int = OPT_LEVEL, *, entry: tuple | None = None, **options):
    """``numba.njit(cache=True, **options)`` compiled at LLVM optimisation level ``opt``
    (:data:`OPT_LEVEL`; :class:`OptimisationLevel`), falling back to a private temporary cache
    directory and then to no cache when numba finds nowhere to write one; ``entry``: the types of the
    arguments Python passes, for the AOT build (see the module)."""

    def decorate(func) -> Kernel:
        kernel = Kernel(func, opt, options, entry)
        if entry is not None:
            ENTRY_POINTS[kernel.name] = kernel
        return kernel

    return decorate


# ----------------------------------------------------------------------------- ahead of time


def aot_symbol(name: str) -> str:
    """The AOT module's name of the entry point ``name`` (``module.qualname``)."""
    return name.removeprefix("stewart_calib.").replace(".", "__")


def source_digests() -> dict[str, str]:
    """SHA-256 of the source of every :data:`KERNEL_MODULES` module, read without importing it."""
    return {
        module: hashlib.sha256(
            (PACKAGE_DIR / (module.removeprefix("stewart_calib.").replace(".", "/") + ".py")).read_bytes()
        ).hexdigest()
        for module in KERNEL_MODULES
    }


@functools.cache
def aot_functions() -> dict[str, Any]:
    """The AOT module's function of each entry point, by :attr:`Kernel.name`; empty where the module
    is absent, cannot load, or was built from other kernel sources or for another processor than
    this one (``STEWART_CALIB_AOT=0`` also empties it: the JIT path alone)."""
    if os.environ.get("STEWART_CALIB_AOT", "1") == "0":
        return {}
    try:
        module = importlib.import_module(AOT_MODULE)
        manifest = json.loads(getattr(module, AOT_MANIFEST)())
        if manifest["sources"] != source_digests() or manifest["cpu"] not in ("generic", processor()):
            return {}
        return {name: getattr(module, aot_symbol(name)) for name in manifest["entries"]}
    except (OSError, ValueError, KeyError, ImportError, AttributeError):
        return {}


def processor() -> list[str]:
    """This machine's processor as LLVM names it, ``[name, features]`` (what numba's cache keys on too)."""
    llvm: Any = importlib.import_module("llvmlite.binding")  # ships no type information

    return [llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten()]


def aot_target() -> str | list[str]:
    """What the AOT build compiles for (its manifest's ``cpu``): ``generic`` or this :func:`processor`."""
    return processor() if AOT_TARGET_CPU == "host" else "generic"


# ----------------------------------------------------------------------------- JIT


def _private_temporary_dir() -> str | None:
    """``<tmp>/stewart-calib-numba-<uid>``, made if needed; None unless it is a directory that
    this user owns and no one else can write (another user's cache would be code we run)."""
    path = Path(tempfile.gettempdir()) / f"stewart-calib-numba-{os.getuid()}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        info = path.lstat()
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return None
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return None
    return str(path)


def _cached_njit(func, options: dict):
    numba, numba_config = load_numba()
    try:
        return _keyed_on_kernel_sources(numba.njit(cache=True, **options)(func))
    except RuntimeError as err:
        if "cannot cache" not in str(err):
            raise
    fallback = _private_temporary_dir()
    if fallback is not None and numba_config.CACHE_DIR != fallback:
        numba_config.CACHE_DIR = fallback  # numba reads it for every later function too
        try:
            return _keyed_on_kernel_sources(numba.njit(cache=True, **options)(func))
        except RuntimeError as err:
            if "cannot cache" not in str(err):
                raise
    return numba.njit(cache=False, **options)(func)


@functools.cache
def kernel_sources_stamp() -> str:
    """One SHA-256 over :func:`source_digests`: every kernel module's source."""
    return hashlib.sha256(json.dumps(source_digests(), sort_keys=True).encode()).hexdigest()


def _keyed_on_kernel_sources(dispatcher):
    """``dispatcher`` with its cache index keyed on every kernel module's source too.

    numba keys a function's cached machine code on its own file's modification time and size alone, and
    that code holds every kernel it calls, those of other modules included (numba's documented limit: a
    change to a symbol defined in another file is not seen): robust.py's kernels hold kalman.py's, and
    after a change to kalman.py alone (a checkout, an edit in an editable install) they would run its old
    code from the cache. With :func:`kernel_sources_stamp` in the key, a change to any kernel module
    compiles every kernel again. The stamp is numba's attribute
    (``IndexDataCacheFile._source_stamp``, read when an index is loaded and written with it); a numba
    without it keeps its own key."""
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = (cache_file._source_stamp, kernel_sources_stamp())
    return dispatcher


@functools.cache
def load_numba() -> tuple[Any, Any]:
    """numba and its configuration (``CACHE_DIR``, ``OPT``: set from the environment when it loads;
    its stubs list none), imported on the first kernel that needs its dispatcher (~0.25 s), with
    :data:`COMPILE_NOTICE` and :data:`OPTIMISATION_LEVEL` listening to its compiles."""
    import numba
    from numba.core import config, event

    class Relay(event.Listener):
        def __init__(self, listener):
            self.listener = listener

        def on_start(self, event) -> None:
            self.listener.on_start(event)

        def on_end(self, event) -> None:
            self.listener.on_end(event)

    event.register("numba:compile", Relay(COMPILE_NOTICE))
    event.register("numba:compile", Relay(OPTIMISATION_LEVEL))
    return numba, config


class OptimisationLevel:
    """numba optimises every function at ``NUMBA_OPT`` (default 3), one setting for the process. Our
    kernels' compiles (numba's ``numba:compile`` event, a cache miss, inside numba's compiler lock)
    run at their own level, with the numba functions they pull in; the level numba reads
    (``numba.core.config.OPT``, read at each pass manager it builds) is restored after. An explicit
    ``NUMBA_OPT`` in the environment wins."""

    def __init__(self):
        self.levels: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self._saved: list = []

    def on_start(self, event) -> None:
        numba_config = load_numba()[1]
        self._saved.append(numba_config.OPT)
        level = self.levels.get(event.data["dispatcher"])
        if level is not None and "NUMBA_OPT" not in os.environ:
            numba_config.OPT = numba_config._OptLevel(level)

    def on_end(self, event) -> None:
        load_numba()[1].OPT = self._saved.pop()


class CompileNotice:
    """numba's ``numba:compile`` event fires only for a kernel not found in the cache: the first
    one a process compiles prints one line on standard error when that is a terminal (piped
    output stays quiet, as progress bars do)."""

    def __init__(self):
        self.told = False

    def on_start(self, event) -> None:
        if not self.told and sys.stderr.isatty():
            self.told = True
            print(
                "stewart-calib: compiling numeric kernels that the installation did not compile ahead of time "
                "(10–30 s, once; later runs load them from the cache)",
                file=sys.stderr,
                flush=True,
            )

    def on_end(self, event) -> None:
        pass


COMPILE_NOTICE = CompileNotice()
OPTIMISATION_LEVEL = OptimisationLevel()
