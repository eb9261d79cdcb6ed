"""Build of the optional compiled inner loop; everything else is in pyproject.toml.

The extension needs only a C compiler and the Python headers. If it cannot be
built, shearfit still installs and runs on its numpy implementation of the
same loop (slower).
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class OptionalBuildExt(build_ext):
    def run(self):
        try:
            super().run()
        except Exception as exc:  # pragma: no cover - depends on the machine
            print(f"shearfit: compiled kernel not built ({exc}); using the numpy implementation")

    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as exc:  # pragma: no cover
            print(f"shearfit: compiled kernel not built ({exc}); using the numpy implementation")


setup(
    # -fno-trapping-math: loops holding float-to-integer conversions and selects vectorise (the binning's)
    ext_modules=[Extension("shearfit.engine._kernels", ["src/shearfit/engine/_kernels.c"],
                           extra_compile_args=["-O3", "-fno-math-errno", "-fno-trapping-math"], libraries=["m"])],
    cmdclass={"build_ext": OptionalBuildExt},
)
