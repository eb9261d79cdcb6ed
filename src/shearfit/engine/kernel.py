"""The compiled inner loops and the choice between them and numpy.

The likelihood's hot loops (model sums, mode binning, the flux-position and
size marginals) are written twice: in C (``_kernels.c``, built at install
time) and in numpy. Both compute the same sums; the C loops are several times
faster. This module is the one place that loads the compiled module:

- ``SHEARFIT_NO_KERNEL=1`` in the environment selects the numpy loops;
- without a compiled module (no C compiler at install time, or a failed
  build) the numpy loops run and a warning says so, once, at import;
- :func:`kernel_info` names the loops in use and, for the compiled ones, the
  instruction-set level the CPU runs them at; the shear catalogue's header
  records it.
"""

from __future__ import annotations

import os
import warnings

__all__ = ["KERNEL", "USE_KERNEL", "kernel_info"]

try:
    from . import _kernels as KERNEL
except ImportError as exc:  # pragma: no cover - depends on the build
    KERNEL = None
    _IMPORT_ERROR = str(exc)
else:
    _IMPORT_ERROR = ""

#: The compiled loops run (else the numpy ones).
USE_KERNEL = KERNEL is not None and os.environ.get("SHEARFIT_NO_KERNEL", "") == ""

if KERNEL is None and os.environ.get("SHEARFIT_NO_KERNEL", "") == "":  # pragma: no cover - depends on the build
    warnings.warn("shearfit: the compiled kernel (shearfit.engine._kernels) is not built "
                  f"({_IMPORT_ERROR}); the numpy loops run instead, several times slower. "
                  "Reinstall with a C compiler (pip install -e .) or set SHEARFIT_NO_KERNEL=1 to silence this.",
                  stacklevel=2)


def kernel_info() -> dict:
    """The inner loops in use: ``path`` ('compiled' or 'numpy'), ``isa``, ``compiler``, ``multiversion``.

    ``isa`` is the instruction-set level at which the CPU runs the compiled
    loops (the run-time choice among the multiversioned builds), or 'numpy'.
    """
    if KERNEL is None:
        return {"path": "numpy", "isa": "numpy", "compiler": "", "multiversion": "",
                "reason": "not built" if _IMPORT_ERROR else ""}
    build = KERNEL.build_info()
    info = {"path": "compiled" if USE_KERNEL else "numpy", "isa": KERNEL.kernel_isa() if USE_KERNEL else "numpy",
            "compiler": build["compiler"], "multiversion": build["multiversion"]}
    if not USE_KERNEL:
        info["reason"] = "SHEARFIT_NO_KERNEL is set"
    return info
