"""Build of the compiled inner loops; everything else is in pyproject.toml.

The extension needs only a C compiler and the Python headers. Where it cannot
be built, shearfit still installs and runs on its numpy loops (several times
slower): the build prints why, and ``import shearfit`` warns once
(``shearfit.engine.kernel``). ``SHEARFIT_REQUIRE_KERNEL=1`` makes a failed
build an error instead (CI sets it, so that a broken kernel cannot pass as a
slow one).
"""

import os
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
        try:
            super().build_extension(ext)
        except Exception as exc:  # pragma: no cover
            self._failed(exc)

    @staticmethod
    def _failed(exc):  # pragma: no cover
        if REQUIRED:
            raise exc
        bar = "*" * 78
        print(f"{bar}\nshearfit: WARNING: the compiled kernel was not built ({exc}).\n"
              f"shearfit will run on its numpy loops, several times slower. Install a C compiler and the\n"
              f"Python headers and reinstall, or set SHEARFIT_REQUIRE_KERNEL=1 to make this an error.\n{bar}",
              file=sys.stderr)


setup(
    # -fno-trapping-math: loops holding float-to-integer conversions and selects vectorise (the binning's)
    ext_modules=[Extension("shearfit.engine._kernels", ["src/shearfit/engine/_kernels.c"],
                           extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math"], libraries=["m"])],
    cmdclass={"build_ext": OptionalBuildExt},
)
