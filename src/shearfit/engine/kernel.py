"""The compiled inner loops and the choice between them and numpy.

The likelihood's hot loops (model sums, mode binning, the flux-position and
size marginals), and the pipeline's isophote analysis (sec. 3.6), are written
twice: in C (``_kernels.c``, built at install time) and in numpy. Both
compute the same sums; the C loops are several times faster. The C module
is built once per instruction-set level: ``_kernels`` for the compiler's
baseline and, on x86-64, ``_kernels_v3`` (x86-64-v3: AVX2, FMA) and
``_kernels_v4`` (x86-64-v4: AVX-512). This module is the one place that
loads them:

- by default the highest level that the CPU runs and that was built;
- ``SHEARFIT_ISA`` in the environment forces one: ``avx512`` (or
  ``x86-64-v4``), ``avx2`` (``x86-64-v3``), ``baseline`` (the portable
  build), or ``numpy`` (the numpy loops; ``SHEARFIT_NO_KERNEL=1`` means the
  same), so that a figure measured on one CPU can be checked on another; a
  level that this CPU cannot run or that was not built falls back to the best
  one available, with a warning;
- without any compiled module (no C compiler at install time, or a failed
  build) the numpy loops run and a warning says so, once, at import;
- :func:`kernel_info` names the loops in use; the shear catalogue's header
  records them (``SFKERNEL``, ``SFISA``).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import warnings

__all__ = ["KERNEL", "USE_KERNEL", "kernel_info", "LEVELS", "special_capsules"]

#: Instruction-set levels, lowest first: (name, module, the SHEARFIT_ISA values that select it).
LEVELS = (("baseline", "_kernels", ("baseline", "portable", "x86-64", "default")),
          ("x86-64-v3", "_kernels_v3", ("avx2", "x86-64-v3", "v3")),
          ("x86-64-v4", "_kernels_v4", ("avx512", "avx-512", "x86-64-v4", "v4")))
_NUMPY = ("numpy", "none", "off")


def _import(module):
    try:
        return importlib.import_module(f".{module}", __package__), ""
    except ImportError as exc:  # pragma: no cover - depends on the build
        return None, str(exc)


def _load():
    """(module or None, why the numpy loops run or a forced level was not taken, the request)."""
    request = os.environ.get("SHEARFIT_ISA", "").strip().lower()
    if os.environ.get("SHEARFIT_NO_KERNEL", "") not in ("", "0") or request in _NUMPY:
        return None, "numpy loops requested (SHEARFIT_ISA=numpy or SHEARFIT_NO_KERNEL)", request or "numpy"
    base, err = _import("_kernels")
    if base is None:  # pragma: no cover - depends on the build
        warnings.warn(f"shearfit: the compiled kernel (shearfit.engine._kernels) is not built ({err}); the numpy "
                      "loops run instead, several times slower. Reinstall with a C compiler (pip install -e .) or "
                      "set SHEARFIT_ISA=numpy to silence this.", stacklevel=3)
        return None, "not built", request
    cpu = set(base.cpu_levels())
    note = ""
    if request and request != "auto":
        wanted = next(((name, module) for name, module, keys in LEVELS if request in keys), None)
        if wanted is None:
            valid = sorted({k for _, _, keys in LEVELS for k in keys} | set(_NUMPY) | {"auto"})
            note = f"SHEARFIT_ISA={request!r} is not a level (valid: {', '.join(valid)})"
        elif wanted[0] not in cpu:
            note = f"this CPU does not run {wanted[0]}"
        else:
            mod = base if wanted[1] == "_kernels" else _import(wanted[1])[0]
            if mod is not None:
                return mod, "", request
            note = f"{wanted[0]} was not built"
        warnings.warn(f"shearfit: SHEARFIT_ISA={request}: {note}; using the best level available", stacklevel=3)
    for name, module, _ in reversed(LEVELS):
        if name in cpu:
            mod = base if module == "_kernels" else _import(module)[0]
            if mod is not None:
                return mod, note, request
    return base, note, request  # pragma: no cover - the baseline is always in cpu


KERNEL, _NOTE, _REQUEST = _load()

#: The compiled loops run (else the numpy ones).
USE_KERNEL = KERNEL is not None


def special_capsules(name) -> list:
    """The C entry points of ``scipy.special.cython_special``'s ``name`` (its fused versions: the caller
    tries each against the signature it needs); [] where scipy's build does not export them."""
    try:
        from scipy.special import cython_special
        caps = cython_special.__pyx_capi__
    except (ImportError, AttributeError):   # pragma: no cover - depends on scipy's build
        return []
    return [c for k, c in caps.items() if k == name or (k.endswith(name) and k.startswith("__pyx_fuse_")
                                                         and k[len("__pyx_fuse_"):-len(name)].isdigit())]


def _found(module) -> bool:
    """Whether a compiled module is installed: found, not imported (a module built for a level this CPU lacks
    must not be loaded)."""
    try:
        return importlib.util.find_spec(f"{__package__}.{module}") is not None
    except (ImportError, ValueError):  # pragma: no cover - a broken or blocked installation
        return False


def kernel_info() -> dict:
    """The inner loops in use.

    Returns
    -------
    dict
        ``path`` ('compiled' or 'numpy'); ``isa``, the instruction-set level of
        the compiled module loaded (or 'numpy'); ``cpu_levels``, the levels this
        CPU runs; ``built``, the levels installed; ``compiler``; ``requested``,
        the value of ``SHEARFIT_ISA`` ('' for the default choice); ``note``, why
        a requested level was not taken or why the numpy loops run.
    """
    built = tuple(name for name, module, _ in LEVELS if _found(module))
    info = {"path": "compiled" if USE_KERNEL else "numpy", "isa": "numpy", "cpu_levels": (), "built": built,
            "compiler": "", "requested": _REQUEST, "note": _NOTE}
    if KERNEL is not None:
        info.update(isa=KERNEL.kernel_isa(), cpu_levels=tuple(KERNEL.cpu_levels()),
                    compiler=KERNEL.build_info()["compiler"])
    return info
