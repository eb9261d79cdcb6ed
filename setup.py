"""Build of the compiled inner loops; everything else is in pyproject.toml.

The extension needs only a C compiler and the Python headers. It is built
once for the compiler's baseline (``shearfit.engine._kernels``) and, on
x86-64 with GCC or clang, twice more for the x86-64-v3 (AVX2) and x86-64-v4
(AVX-512) levels, each file whole; ``shearfit.engine.kernel`` imports the
best the CPU runs (``SHEARFIT_ISA`` chooses another). Where a level cannot be
built the others still install; where none can, shearfit runs on its numpy
loops (several times slower): the build prints why, and ``import shearfit``
warns once. ``SHEARFIT_REQUIRE_KERNEL=1`` makes a failed build an error
instead (CI sets it, so that a broken kernel cannot pass as a slow one).
"""

import os
import platform
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

REQUIRED = os.environ.get("SHEARFIT_REQUIRE_KERNEL", "") not in ("", "0")


class OptionalBuildExt(build_ext):
    def run(self):
        try:
            super().run()
        except Exception as exc:  # pragma: no cover - depends on the machine
            self._failed(exc)

    def build_extension(self, ext):
        fallbacks = list(getattr(ext, "fallback_args", []))
        while True:
            try:
                super().build_extension(ext)
                return
            except Exception as exc:  # pragma: no cover - depends on the compiler
                if fallbacks:           # an older compiler: the same level by the CPU that defines it
                    ext.extra_compile_args = ext.extra_compile_args[:-1] + [fallbacks.pop(0)]
                    continue
                self._failed(exc, ext.name)
                return

    @staticmethod
    def _failed(exc, name="shearfit.engine._kernels"):  # pragma: no cover
        if REQUIRED:
            raise exc
        bar = "*" * 78
        print(f"{bar}\nshearfit: WARNING: {name} was not built ({exc}).\n"
              f"shearfit runs the other levels built, or its numpy loops (several times slower) without\n"
              f"any. Install a C compiler and the Python headers and reinstall, or set\n"
              f"SHEARFIT_REQUIRE_KERNEL=1 to make this an error.\n{bar}",
              file=sys.stderr)


FLAGS = ["-O3", "-fno-math-errno", "-fno-trapping-math"]


def kernel_extensions():
    """The baseline module and, on x86-64 with a GCC-like compiler, the AVX2 and AVX-512 ones."""
    src = "src/shearfit/engine/"
    exts = [Extension("shearfit.engine._kernels", [src + "_kernels.c"], extra_compile_args=FLAGS,
                      libraries=["m"], depends=[src + "_kernels.c"])]
    if platform.machine().lower() in ("x86_64", "amd64") and sys.platform != "win32":
        for level, fallback in (("v3", "-march=haswell"), ("v4", "-march=skylake-avx512")):
            ext = Extension(f"shearfit.engine._kernels_{level}", [src + f"_kernels_{level}.c"],
                            extra_compile_args=FLAGS + [f"-march=x86-64-{level}"], libraries=["m"],
                            depends=[src + "_kernels.c"])
            ext.fallback_args = [fallback]
            exts.append(ext)
    return exts


setup(
    # -fno-trapping-math: loops holding float-to-integer conversions and selects vectorise (the binning's)
    ext_modules=kernel_extensions(),
    cmdclass={"build_ext": OptionalBuildExt},
)
