"""One exposure of one object (:class:`Observation`) and a fit's result.

Conventions (docs/interface.rst): arrays are indexed ``image[y, x]``; pixel centres
sit at integer indices; the stamp centre is pixel ``(ny // 2, nx // 2)``. The
Jacobian maps pixel offsets to the catalogue's tangent-plane frame (u, v) in
arcsec, +u west, +v north::

    [du, dv]^T = J [dx, dy]^T,   J = [[du/dx, du/dy], [dv/dx, dv/dy]]
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .errors import ShearfitValueError

__all__ = ["Observation", "FitResult"]


def _readonly(a, name, ndim=2):
    if is_immutable(a) and a.dtype == np.float64:
        arr = a   # immutable (is_immutable; a PSF image a CCD's objects share): shared, not copied
    else:
        arr = np.array(a, dtype=np.float64, copy=True)
    if arr.ndim != ndim:
        raise ShearfitValueError(f"Observation {name} must be a {ndim}D array, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


def _finite(a) -> bool:
    """Whether every value of a small array is finite (on Python floats: cheaper than numpy's calls on arrays
    this small)."""
    return all(map(math.isfinite, a.ravel().tolist()))


#: The sums of immutable PSF images already checked, by id: (a weak reference to the array, its sum). A CCD's
#: objects share one PSF image; an immutable array's sum cannot change.
_PSF_SUMS: dict = {}


def _psf_sum(psf) -> float:
    if not is_immutable(psf):
        return float(psf.sum())
    hit = _PSF_SUMS.get(id(psf))
    if hit is not None and hit[0]() is psf:
        return hit[1]
    if len(_PSF_SUMS) >= 256:
        _PSF_SUMS.clear()
    total = float(psf.sum())
    _PSF_SUMS[id(psf)] = (weakref.ref(psf), total)
    return total


def _checked_weight(weight, image):
    """A weight map as an Observation keeps it (read-only float64), checked: the image's shape, finite and
    non-negative."""
    w = _readonly(weight, "weight")
    if w.shape != image.shape:
        raise ShearfitValueError(f"Observation weight shape {w.shape} differs from image shape {image.shape}")
    if w.size and not (w.min() >= 0 and math.isfinite(w.max())):   # (NaN fails the first)
        raise ShearfitValueError("Observation weight must be finite and non-negative")
    return w


def _checked_psf(psf):
    """A PSF image as an Observation keeps it (read-only float64), checked to sum to 1."""
    out = _readonly(psf, "psf")
    psum = _psf_sum(out)
    if not math.isfinite(psum) or abs(psum - 1.0) > 1e-3:
        raise ShearfitValueError(f"Observation psf must sum to 1 (sums to {psum:.6g})")
    return out


def _checked_moffat(psf_moffat):
    """An App. A Moffat (rs, beta) as an Observation keeps it (Python floats), checked; None stays None."""
    if psf_moffat is None:
        return None
    rs, beta = (float(v) for v in psf_moffat)
    if not (rs > 0 and beta > 1 and np.isfinite(rs) and np.isfinite(beta)):
        raise ShearfitValueError(f"Observation psf_moffat must be (rs > 0, beta > 1), got {psf_moffat!r}")
    return rs, beta


def is_immutable(a) -> bool:
    """Whether ``a`` is a read-only C-contiguous array that owns its memory, or a read-only C-contiguous view of
    one (such as an image of a read-only stack): no view of it can change its values (short of the owner being
    made writable again; numpy makes no view writable while its owner is read-only)."""
    if not isinstance(a, np.ndarray) or a.flags.writeable or not a.flags.c_contiguous:
        return False
    base = a.base
    return base is None or (type(base) is np.ndarray and base.base is None and not base.flags.writeable)


class Observation:
    """A postage stamp of one object on one exposure, with what is needed to model it.

    Parameters
    ----------
    image : 2D array
        Background-subtracted counts.
    weight : 2D array, optional
        Inverse variance per pixel, 0 where unusable. Without it the noise is
        estimated from the stamp (median absolute deviation).
    psf : 2D array
        PSF including the pixel response, summing to one, centred on pixel
        ``(ny // 2, nx // 2)`` of its own array.
    psf_oversampling : int
        PSF array pixels per image pixel.
    jacobian : 2x2 array
        Local ``d(u, v)/d(x, y)`` in arcsec per pixel at the object.
    offset : (dx, dy)
        The object's nominal position minus the stamp centre, in pixels.
    flux_scale : float
        Counts in this exposure per unit of the common flux.
    psf_moffat : (rs, beta), optional
        For a native PSF, the circular Moffat (scale radius in pixels, beta)
        that carries it above Nyquist (App. A; see :func:`shearfit.engine.model.psf_moffat`).
        The pipeline fits one per CCD; by default one is fitted to ``psf``.

    The arrays are kept as read-only float64 copies, except a float64 array that is already read-only and
    owns its memory, or is a read-only view of one that does (no view of it can change it: ``is_immutable``):
    that one is kept itself, so that many observations sharing one PSF image (a CCD's objects) share the array
    too, as metacal's versions share their stack of images.
    """

    def __init__(self, image, psf, jacobian, weight=None, psf_oversampling=1, offset=(0.0, 0.0),
                 flux_scale=1.0, psf_moffat=None):
        self.image = _readonly(image, "image")
        if weight is None:
            sigma = _mad_sigma(self.image)
            weight = np.full(self.image.shape, 1.0 / sigma**2)
        self.weight = _checked_weight(weight, self.image)
        self.psf = _checked_psf(psf)
        k = int(psf_oversampling)
        if k < 1 or k != psf_oversampling:
            raise ShearfitValueError(f"Observation psf_oversampling must be a positive integer, got {psf_oversampling!r}")
        self.psf_oversampling = k
        J = np.array(jacobian, dtype=np.float64)
        if not (J.shape == (2, 2) and _finite(J) and abs(J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]) > 0):
            raise ShearfitValueError("Observation jacobian must be a finite, invertible 2x2 array")
        J.setflags(write=False)
        self.jacobian = J
        off = np.array(offset, dtype=np.float64)
        if off.shape != (2,) or not _finite(off):
            raise ShearfitValueError("Observation offset must be a pair of finite numbers (dx, dy)")
        off.setflags(write=False)
        self.offset = off
        self.flux_scale = float(flux_scale)
        if not self.flux_scale > 0:
            raise ShearfitValueError("Observation flux_scale must be positive")
        self.psf_moffat = _checked_moffat(psf_moffat)

    def with_image(self, image):
        """This observation with other pixels (same weight, PSF, Jacobian, offset, scale and Moffat, whose
        arrays are shared, already checked): another version of the same stamp, as metacalibration's."""
        img = _readonly(image, "image")
        if img.shape != self.image.shape:
            raise ShearfitValueError(f"Observation image shape {img.shape} differs from {self.image.shape}")
        out = object.__new__(Observation)
        out.__dict__.update(self.__dict__)
        out.image = img
        return out

    def derived(self, image, weight, psf, psf_moffat=None):
        """An observation of the same stamp geometry (Jacobian, offset, flux scale, PSF oversampling) with other
        pixels, weights, PSF image and Moffat, made from this checked one (metacalibration's versions): the new
        arrays checked as the constructor checks them, the geometry's taken as they are. Arrays that are immutable
        float64 are kept themselves (read-only copies of the others)."""
        img = _readonly(image, "image")
        wgt = _checked_weight(weight, img)
        out = object.__new__(Observation)
        out.__dict__.update(self.__dict__)
        out.image, out.weight = img, wgt
        out.psf = _checked_psf(psf)
        out.psf_moffat = _checked_moffat(psf_moffat)
        return out

    @property
    def shape(self):
        return self.image.shape

    @property
    def pixel_scale(self) -> float:
        """sqrt(|det J|): the local linear pixel size in arcsec (made once per Jacobian)."""
        made = self.__dict__.get("_pixel_scale")
        if made is None or made[0] is not self.jacobian:
            made = self._pixel_scale = (self.jacobian, float(np.sqrt(abs(np.linalg.det(self.jacobian)))))
        return made[1]

    def __repr__(self):
        return (f"Observation(shape={self.shape}, psf_shape={self.psf.shape}, "
                f"psf_oversampling={self.psf_oversampling}, offset={tuple(self.offset)}, "
                f"flux_scale={self.flux_scale})")


def _mad_sigma(image):
    x = image[np.isfinite(image)]
    med = np.median(x)
    s = 1.4826 * np.median(np.abs(x - med))
    if not s > 0:
        raise ShearfitValueError("cannot estimate the noise of a stamp without weights: it has no scatter")
    return s


@dataclass
class FitResult:
    """What :func:`shearfit.measure_object` returns for one object.

    ``e1, e2`` are the likelihood-mean ellipticity (sec. 3.4), ``e_var`` the 1D
    variance of the likelihood surface, ``weight`` eq. (weight), ``snr`` the
    profile-weighted signal-to-noise ratio over all exposures, ``scalelength``
    (arcsec, disk semi-major axis), ``bulge_fraction`` and ``model_flux``
    posterior means; ``fitclass`` one of the codes in :mod:`shearfit.errors`.
    ``weight`` is zero for stars; ``shape_weight`` is eq. (weight) whatever
    the classification. ``star_pvalue`` is the F-test probability that the
    galaxy model's improvement over a point source is chance, and
    ``centroid_shift`` the fitted centre's distance from the input position
    in pixels; ``n_samples`` and ``n_models`` count ellipticity samples and
    (e, r) models evaluated. With the ``self_calibration`` setting, ``e1, e2``
    are self-calibrated, ``selfcal_de`` is the correction subtracted from the
    likelihood mean and ``selfcal_response`` the estimator's response found
    on the model (radial, tangential; before bounding), and ``selfcal_steps`` the Newton steps taken
    (``self_calibration_steps`` at most; the further ones damped); otherwise None, None and 0.
    With the ``noise_bias_correction`` setting, ``noise_bias_de`` is the noise
    bias (e1, e2) found by noise-bias extrapolation and subtracted (as scaled
    where the corrected estimate would lie beyond ``model_e_limit``), and
    ``noise_bias_de_one_pair`` what the pair at the full amplitude alone
    subtracts (the same without ``noise_bias_second_amplitude``); otherwise
    None. ``flux_snr`` is the SNR ``model_flux`` would have were the object a
    point source (on the same exposures), and ``round_scalelength`` the
    likelihood mean of the scalelength of the round model of each sample's
    area, ``r sqrt(q)``: neither depends on the object's shape, so a shear
    leaves both unchanged to first order where it changes ``snr`` and
    ``scalelength`` (the axes of :func:`shearfit.calib.weights.isotropic_weights`).
    """

    e1: float = np.nan
    e2: float = np.nan
    e_var: float = np.nan
    weight: float = 0.0
    snr: float = np.nan
    scalelength: float = np.nan
    bulge_fraction: float = np.nan
    model_flux: float = np.nan
    fitclass: int = -2
    n_exposures_used: int = 0
    star_pvalue: float = np.nan
    centroid_shift: float = np.nan
    n_samples: int = 0
    n_models: int = 0
    shape_weight: float = 0.0
    flux_snr: float = np.nan
    round_scalelength: float = np.nan
    message: str = ""
    samples: Optional[np.ndarray] = field(default=None, repr=False)
    selfcal_de: Optional[tuple] = field(default=None, repr=False)
    selfcal_response: Optional[tuple] = field(default=None, repr=False)
    selfcal_steps: int = field(default=0, repr=False)
    noise_bias_de: Optional[tuple] = field(default=None, repr=False)
    noise_bias_de_one_pair: Optional[tuple] = field(default=None, repr=False)
