"""The memory one object's fit needs, estimated before the fit (the setting ``max_object_memory_mb``).

The fit's arrays scale with its Fourier modes (:mod:`shearfit.engine.model`): each exposure's stamp of
side n has ``n (n//2 + 1)`` sampled (rfft) modes, and the model lives on a grid s times finer in each
direction (s = ``alias_oversampling``, 3, for a native PSF with the App. A Moffat correction; the PSF's
own oversampling k for an oversampled one; 1 for a native PSF without the correction), of which only
the modes where the PSF's transform is above ``psf_mode_tolerance`` are kept: a band of the frequency
plane whose area goes as 1 / FWHM^2. Every later array of the fit (the joint modes, the fold groups'
matrix, the kernel's packed rows, the mode bins) is at most a few per kept mode; what the ellipticity
sampling holds (a few hundred samples of 7 sizes and 7 fluxes) is small against them.

The estimate, in bytes, for an object on E exposures with stamps of side n::

    B = 2 MiB                                       # fixed: sampling, bins, tables
        + 450 sum_i n (n//2 + 1) min(s_i^2, 36 / w_i^2)   # per kept Fourier mode of exposure i
        + 200 s^2 n (n//2 + 1)                      # one exposure's full fine grid, alias tables
        + 64 E n^2                                  # stamps, weights, masks, the co-add (sec. 3.6)

times 2 for metacalibration (five versions of the stamps and their transforms); w_i is exposure i's
PSF FWHM in its native pixels (unknown: the bound s_i^2, every fine mode), s the largest s_i. The
coefficients are calibrated on the tracemalloc peak of :func:`shearfit.measure_object` for 1 to 14
exposures with stamps of 48 to 128 pixels (faint and bright galaxies, Moffat PSFs of 0.3 to 1.1 arcsec
FWHM at 0.187 arcsec per pixel, the engine of commit 24804ee): 450 bytes per mode is the most any fit
took per mode kept by the PSF cut (the bright ones, whose noise-aware cut keeps most modes), and 36 / w^2
bounds the modes Moffat PSFs with beta 2.5 to 4.5 and up to 1 arcsec FWHM keep (20-36 / w^2 per sampled
mode); PSFs with heavier wings keep more (beta 2: up to 46 / w^2, beta 1.5: up to 61 / w^2), which the
margin of the bytes per mode (450 against the 170-300 of most fits) covers. ``benchmarks/memory.py``
prints the estimate beside the measured peaks (tracemalloc and RSS, each case in a fresh process): 1.25
to 2.6 times them (the engine of 2026-11-25, whose fold groups are binned) for 7 exposures on stamps of
48-128 pixels, the largest galaxies and a sharp PSF (the
loosest for faint galaxies, whose noise-aware cut drops two thirds of the modes). Without the compiled loops
(``SHEARFIT_ISA=numpy``), the numpy lines' model sums take their models in blocks of
``likelihood.NUMPY_BLOCK_ELEMENTS`` (model, mode) pairs, so that the estimate bounds them too (0.4-0.6 times
it on those cases; until session 82 they took a sampler's chunk at once, 10-15 times it). A change of the engine
that holds more per mode (per ellipticity and fold-group mode, say) needs these coefficients measured again.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_memory_bytes", "fine_grid_factor"]

#: bytes of the fit per Fourier mode kept by the PSF cut
BYTES_PER_MODE = 450.0
#: the modes above the PSF cut per sampled mode: about this / FWHM^2 (FWHM in native pixels)
PSF_MODE_AREA = 36.0
#: bytes per fine-grid mode of the largest exposure grid: its transient full grid and the alias tables
BYTES_PER_GRID_MODE = 200.0
#: bytes per stamp pixel and exposure in the pipeline before the fit (stamps, weights, masks, co-add)
BYTES_PER_PIXEL = 64.0
#: the fixed part: the ellipticity samples, mode bins, spline and profile tables
BASE_BYTES = 2.0 * 2 ** 20
#: metacalibration's factor (five versions of each stamp, their transforms and GalSim's images)
METACAL_FACTOR = 2.0


def fine_grid_factor(fit, psf_oversampling=1) -> int:
    """s: the fine grid's refinement per axis (``alias_oversampling`` for a native PSF with the Moffat
    correction, the PSF's oversampling k for an oversampled one, else 1)."""
    k = int(psf_oversampling)
    if k > 1:
        return k
    return int(fit.alias_oversampling) if fit.alias_correction == "moffat" else 1


def fit_memory_bytes(side, n_exposures, fit, psf_fwhm=None, psf_oversampling=1, metacal=False) -> float:
    """Estimated peak memory, bytes, of one object's fit on ``n_exposures`` stamps of ``side`` pixels.

    Parameters
    ----------
    side : int
        The stamp side, pixels.
    n_exposures : int
        The exposures the object is fitted on.
    fit : FitConfig
        The engine's settings (``alias_correction``, ``alias_oversampling``).
    psf_fwhm : float or sequence of float, optional
        Each exposure's PSF FWHM in its native pixels (one value for all); None or NaN where unknown,
        which counts every mode of the fine grid (the bound for any PSF).
    psf_oversampling : int or sequence of int
        Each exposure's PSF oversampling k (1: native).
    metacal : bool
        The object is measured by metacalibration.

    The formula is in the module's docstring; it is an upper bound of the measured peak, within a factor
    of about 3.
    """
    side = int(side)
    n = int(n_exposures)
    if n <= 0 or side <= 0:
        return BASE_BYTES
    ks = np.broadcast_to(np.asarray(psf_oversampling, dtype=np.int64), (n,))
    w = np.broadcast_to(np.asarray(np.nan if psf_fwhm is None else psf_fwhm, dtype=float), (n,))
    s2 = np.array([fine_grid_factor(fit, k) ** 2 for k in ks], dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        band = np.where(np.isfinite(w) & (w > 0), PSF_MODE_AREA / np.where(w > 0, w, 1.0) ** 2, np.inf)
    rfft = side * (side // 2 + 1)
    modes = float(np.sum(rfft * np.minimum(s2, band)))
    total = (BASE_BYTES + BYTES_PER_MODE * modes + BYTES_PER_GRID_MODE * float(s2.max()) * rfft
             + BYTES_PER_PIXEL * n * side * side)
    return total * (METACAL_FACTOR if metacal else 1.0)
