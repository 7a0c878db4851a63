"""The package's one build step beyond pyproject.toml: its numba kernels compiled ahead of time.

``stewart_calib._aot_kernels`` holds every entry point (``stewart_calib._jit.njit(entry=…)``) at
the argument types its Python callers pass, compiled by numba's ``pycc`` for this processor, and
its ``manifest()`` names them with the digests of the kernel sources they were built from and the
processor (stewart_calib._jit checks those before it uses the module). Whatever goes wrong here — no C
compiler, a numba without ``pycc`` — the package installs without it and compiles on first use.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent


def _trampoline(kernel):
    """A function of the tuple of ``kernel``'s arguments that calls it: pycc compiles what it exports
    with its default flags, so the kernel itself (``fastmath``, ``error_model``, its LLVM level) is
    compiled by its dispatcher, as the JIT compiles it (pycc takes no ``*args``: hence the tuple)."""

    def call(arguments):
        return kernel(*arguments)

    return call


def _GilReleasing(flags_class):
    """pycc's compile flags with the GIL released around each exported call, as every kernel's
    ``nogil=True`` has it in the JIT: pycc's own flags hold it, and then the read-ahead thread's
    kernels (the log's residuals before calibration) waited for the filter's instead of running
    beside them (every entry point is nogil: tests/test_aot.py)."""

    class Flags(flags_class):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    return Flags


def _constant(text: str):
    def constant():
        return text

    return constant


class BuildKernels(build_ext):
    def build_extension(self, ext: Extension) -> None:
        started = time.perf_counter()
        try:
            self._build_kernels(ext)
        except Exception as err:  # any failure: install without them; they compile on first use
            print(
                f"stewart-calib: the kernels were not compiled ahead of time ({type(err).__name__}: {err}); "
                "they will compile on first use",
                file=sys.stderr,
            )
            return
        print(
            f"stewart-calib: kernels compiled ahead of time in {time.perf_counter() - started:.0f} s", file=sys.stderr
        )

    def _build_kernels(self, ext: Extension) -> None:
        # a cache of our own: numba must compile every kernel into the module, never link a user's cached code
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="stewart-calib-aot-")
        sys.path.insert(0, str(ROOT))
        import importlib

        from numba import types
        from numba.core import config
        from numba.pycc import CC
        from numba.pycc import compiler as pycc_compiler

        pycc_compiler.Flags = _GilReleasing(pycc_compiler.Flags)

        from stewart_calib import _jit

        _jit.load_numba()  # numba, with the listener that compiles each kernel at its own LLVM level
        for module in _jit.KERNEL_MODULES:
            importlib.import_module(module)
        config.OPT = config._OptLevel(_jit.OPT_LEVEL)  # the module-wide passes, as each kernel's JIT compile
        compiler = CC(ext.name.rpartition(".")[2], source_module=_jit)
        compiler.target_cpu = _jit.AOT_TARGET_CPU
        for name, kernel in _jit.ENTRY_POINTS.items():
            argument_types = tuple(spec.numba_type() for spec in kernel.entry)
            kernel.dispatcher.compile(argument_types)  # for its return type; the trampoline links this code
            signature = kernel.dispatcher.overloads[argument_types].signature.return_type(types.Tuple(argument_types))
            compiler.export(_jit.aot_symbol(name), signature)(_trampoline(kernel))
        manifest = {"entries": list(_jit.ENTRY_POINTS), "sources": _jit.source_digests(), "cpu": _jit.aot_target()}
        compiler.export(_jit.AOT_MANIFEST, types.unicode_type())(_constant(json.dumps(manifest)))
        built = compiler.distutils_extension()
        for attribute in ("sources", "depends", "define_macros", "include_dirs", "libraries", "library_dirs"):
            setattr(ext, attribute, getattr(built, attribute))
        ext.extra_compile_args, ext.extra_link_args = built.extra_compile_args, built.extra_link_args
        built._prepare_object_files(self)
        ext.extra_objects = built.extra_objects
        self.force = True  # its sources are the kernel modules, which setuptools does not compare with the module
        super().build_extension(ext)


setup(
    ext_modules=[Extension("stewart_calib._aot_kernels", sources=[], optional=True)],
    cmdclass={"build_ext": BuildKernels},
)
