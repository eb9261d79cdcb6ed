"""The field pipeline: exposures + catalogue -> shear catalogue (``shearfit measure``).

Per object (sec. 3.6, 4, 6 of the paper):

1. every CCD of every exposure that holds it (``locate_all``);
2. on each, a stamp cut at the integer pixel nearest the catalogue position,
   the sub-pixel remainder carried to the model as a phase (``Observation.offset``),
   never interpolated;
3. the local Jacobian of the WCS at the object: the affine map applied to the
   models before the PSF, so ellipticities come out in the (u, v) frame of
   docs/interface.rst whatever the pixel grid's rotation, flip or distortion;
4. the exposure's PSF at the object (a given image per CCD, or a PSFEx model);
5. the photometric scale from MAGZP, one flux for all exposures;
6. the joint fit (:func:`shearfit.measure_object`), and one catalogue row.

Sec. 3.6 (:mod:`.blends`): on the co-added stamp smoothed by the PSF (built on the
first exposure's pixel grid; an exposure rotated, flipped or distorted against it is
carried onto that grid, and the masks back, to the nearest pixel through the local
Jacobians), neighbours whose 2-sigma isophotes do not touch the object's are masked (set to
background); several significant maxima inside the isophote flag the object
blended or complex (-3), as does another input-catalogue object inside the isophote
(``catalogue_blends``: a pair closer than the PSF, which shows one maximum); an isophote
centroid more than 4 pixels from the input position flags it (-5); an exposure with a
bad pixel inside the isophote is dropped, bad pixels elsewhere are background.
"""

from __future__ import annotations

import functools
import hashlib
import math
import json
import logging
import os
import shutil
import warnings
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
import yaml
from astropy.table import Table

from ..version import __version__
from ..workers import SINGLE_THREAD_ENV, process_pool, single_threaded
from ..files import atomic_path
from ..errors import (FITCLASS_BAD_INPUT, FITCLASS_BLENDED, FITCLASS_FEW_EXPOSURES, FITCLASS_FIT_FAILED, FITCLASS_GALAXY,
                      FITCLASS_MEMORY, FITCLASS_OFF_EXPOSURES, FITCLASS_TOO_LARGE, ShearfitIOError, ShearfitValueError)
from ..calib.calibrate import calibration_m, default_calibration, load_calibration
from ..calib.weights import isotropic_bins, isotropic_weights
from ..engine.measure import measure_object
from ..engine.kernel import KERNEL, USE_KERNEL
from ..engine.model import ContentMemo, inv2, psf_moffat
from ..observation import Observation, is_immutable
from ..io.fieldconfig import CALIBRATION_MODES, FieldConfig
from ..io.fits import (METACAL_QUANTITIES, attach_pixels, bad_rows, detached, empty_output_table, provenance_cards,
                       read_catalog, read_exposure, release_pages, write_catalog_atomic)
from ..io.psfinput import PSFExModel, psf_image_hdus, read_psf_fits
from ..io.stamps import cut_stamp, locate_all
from .blends import analyse_stamps, carry_stamp
from .memory import fit_memory_bytes
from ..io.wcs import local_jacobian, pixel_to_sky
from ..psf.build import (FieldFrame, TooFewStarsError, build_exposure_psf, is_psf_model_file, read_psf_model,
                         stellar_locus)

log = logging.getLogger(__name__)

__all__ = ["measure_field", "calibration_m", "local_cluster_config", "psf_ellipticity", "psf_fwhm_arcsec"]

#: psf_moments' results by the PSF image (the objects of a CCD with one given PSF image share them)
_PSF_MOMENTS = ContentMemo(32 * 2 ** 20)


#: per image shape: HSM's mask (an image of ones: GalSim makes one per call otherwise) and the image's bounds
_HSM_FRAME = {}


def _hsm_frame(shape):
    got = _HSM_FRAME.get(shape)
    if got is None:
        import galsim

        ny, nx = shape
        got = _HSM_FRAME[shape] = (galsim.ImageI(np.ones(shape, np.int32), scale=1.0), galsim.BoundsI(1, nx, 1, ny))
    return got


@functools.lru_cache(maxsize=1)
def _hsm_options():
    """FindAdaptiveMom's ``check=False`` (its checks of mask and image, which :func:`_hsm_frame` makes right),
    where this GalSim has it."""
    import inspect

    import galsim

    return {"check": False} if "check" in inspect.signature(galsim.hsm.FindAdaptiveMom).parameters else {}


def psf_moments(psf, guess_sig=None):
    """Adaptive moments of a PSF image: (sigma in array pixels, reduced shear (g1, g2)), or None if HSM fails.
    ``guess_sig``: HSM's starting size (pixels; 5 if None), e.g. that of a PSF nearby; the iteration then
    converges in fewer steps to the same moments within HSM's precision (1e-6), not to the last bit.

    A read-only image (a given PSF image, which the objects of its CCD share) has its moments remembered by the
    image and the guess (:class:`shearfit.engine.model.ContentMemo`); the guess is part of the key, so that an
    image's moments do not depend on which guess reached it first (a catalogue is then the same for any chunking
    and any number of workers). Any other image (a fitted or PSFEx model's at one object, its own) is measured
    directly: remembering it would cost a copy and a comparison that no later object uses."""
    import galsim

    guess = 5.0 if guess_sig is None else float(guess_sig)

    def make():
        a = np.ascontiguousarray(psf, dtype=np.float64)
        ones, bounds = _hsm_frame(a.shape)
        try:
            # galsim._Image: GalSim's documented light constructor; the mask is ours, of the image's shape
            mom = galsim.hsm.FindAdaptiveMom(galsim._Image(a, bounds, None), weight=ones, guess_sig=guess,
                                             **_hsm_options())
        except Exception:   # noqa: BLE001 - HSM fails on pathological images
            return None
        return mom.moments_sigma, (mom.observed_shape.g1, mom.observed_shape.g2)
    if not is_immutable(psf):
        return make()
    return _PSF_MOMENTS.get(psf, guess, make)


def psf_fwhm_arcsec(jacobian, oversampling=1, moments=None):
    """The PSF's size at the object in arcsec: the FWHM of the Gaussian of its adaptive moments,
    2.3548 sigma, with sigma carried to the sky by the Jacobian (det(M_sky)^(1/4) = sigma sqrt|det J|);
    NaN where the moments failed. The noise-bias calibration's resolution (``scalelength / psf_fwhm``) uses it."""
    if moments is None:
        return np.nan
    (a, b), (c, d) = np.asarray(jacobian, float).tolist()
    return float(2.3548 * moments[0] / oversampling * np.sqrt(abs(a * d - b * c)))


def psf_ellipticity(psf, jacobian, oversampling=1, moments=None):
    """Ellipticity (a-b)/(a+b) of a PSF image in the (u, v) frame, from its adaptive moments.

    The moment matrix found in pixels is carried to the sky by the Jacobian
    (M_sky = J M J^T), then turned into the reduced-shear ellipticity.
    ``moments`` (from :func:`psf_moments`) avoids measuring them again.
    """
    moments = psf_moments(psf) if moments is None else moments
    if moments is None:
        return np.nan, np.nan
    s = moments[0] / oversampling
    g1, g2 = moments[1]
    # moment matrix of an elliptical Gaussian of size s and reduced shear g (det = s^4): s^2 S S^T, S the
    # shear's matrix (GalSim's Shear.getMatrix) [[1 + g1, g2], [g2, 1 - g1]] / sqrt(1 - |g|^2)
    S = np.array([[1 + g1, g2], [g2, 1 - g1]]) / np.sqrt(1 - g1 * g1 - g2 * g2)
    M = (s * s) * S @ S.T
    Ms = jacobian @ M @ jacobian.T
    a, b, c = Ms[0, 0], Ms[1, 1], Ms[0, 1]
    tr = a + b
    det = a * b - c * c
    # distortion (a-b, 2c)/tr -> reduced shear: g = e / (1 + sqrt(1 - |e|^2))
    e1, e2 = (a - b) / tr, 2 * c / tr
    den = 1 + np.sqrt(max(1 - e1 * e1 - e2 * e2, 0.0)) if det > 0 else np.nan
    return e1 / den, e2 / den


@dataclass
class _ExposurePSF:
    images: Optional[list] = None     # one (array, oversampling) per CCD
    psfex: Optional[list] = None      # one PSFExModel per CCD
    fitted: Optional[object] = None   # a shearfit.psf PixelPSF fitted to the exposure's stars
    ccds: Optional[list] = None
    model_ccd: Optional[list] = None  # per CCD of ``ccds``, its index in ``fitted`` (a model file: CCDs may be left out)
    _frame: Optional[FieldFrame] = None
    _moffat: dict = field(default_factory=dict)    # per-CCD Moffat fits; copies made by replace() share it
    _sigma: dict = field(default_factory=dict)     # per-CCD PSF sizes at the centre (HSM's starting guess)
    _moment_splines: dict = field(default_factory=dict)   # per (CCD, grid): splines of the PSF's moments, or None

    def __setstate__(self, state):
        """Unpickled (on a Dask worker, in a spawned pool's worker), the given PSF images are read-only arrays of
        their own again, as when they were read (:func:`_immutable`): an unpickled array is writable or a view of
        the message's buffer, and what the pipeline and the engine remember by PSF image (its adaptive moments,
        Moffat, transforms, alias tables) is remembered only for such images (:func:`shearfit.observation.
        is_immutable`): without this a Dask worker ran GalSim's HSM on the PSF of every object and copied it into
        every Observation."""
        self.__dict__.update(state)
        if self.images is not None:
            self.images = [got if got is None or is_immutable(got[0]) else _immutable(got) for got in self.images]

    def moffat(self, ccd_index, shape):
        """The CCD's above-Nyquist Moffat (rs, beta), fitted once to its PSF at the CCD centre (App. A).

        None for an oversampled PSF (it needs none) or where the centre has no PSF.
        """
        if ccd_index not in self._moffat:
            ny, nx = shape
            got = self.at(ccd_index, 0.5 * (nx - 1), 0.5 * (ny - 1))
            self._moffat[ccd_index] = psf_moffat(got[0]) if got is not None and got[1] == 1 else None
        return self._moffat[ccd_index]

    def sigma_guess(self, ccd_index, shape):
        """HSM's starting size for the CCD's PSFs: the adaptive size of its PSF at the CCD centre (None where
        that has none)."""
        if ccd_index not in self._sigma:
            ny, nx = shape
            got = self.at(ccd_index, 0.5 * (nx - 1), 0.5 * (ny - 1))
            mom = psf_moments(got[0]) if got is not None else None
            self._sigma[ccd_index] = None if mom is None else mom[0]
        return self._sigma[ccd_index]

    def moments_at(self, ccd_index, shape, x, y, psf, grid=0):
        """Adaptive moments of the PSF at CCD pixel (x, y), whose image there is ``psf`` (as :func:`psf_moments`
        returns them). A given image (one per CCD, remembered) is measured by HSM from the CCD's guess; a PSF that
        varies over the CCD (a fitted, PSFEx or Piff model), with ``grid`` >= 4, is measured on grid x grid points
        spanning the CCD and the moments at (x, y) are those points' bicubic splines there
        (:meth:`moment_splines`), so that the CCD's objects cost no HSM call each. ``grid`` = 0, or a grid point
        where HSM fails: HSM on ``psf`` itself."""
        many = self.moments_many(ccd_index, shape, np.array([x], float), np.array([y], float), grid)
        if many is not None:
            return many[0]
        return psf_moments(psf, self.sigma_guess(ccd_index, shape))

    def moments_many(self, ccd_index, shape, x, y, grid):
        """:meth:`moments_at` of a varying PSF at CCD pixels (x, y) (arrays) from the CCD's splines, as a list
        of (sigma, (g1, g2)), in one evaluation per quantity; None where the PSF is given as images, ``grid`` is
        0 or the CCD has no splines (then HSM at each object)."""
        if not grid or self.images is not None:
            return None
        splines = self.moment_splines(ccd_index, shape, grid)
        if splines is None:
            return None
        sigma, g1, g2 = (f.ev(y, x).tolist() for f in splines)
        return [(s, (a, b)) for s, a, b in zip(sigma, g1, g2)]

    def moment_splines(self, ccd_index, shape, grid):
        """Bicubic splines (scipy's RectBivariateSpline, in CCD pixels y, x) through the PSF's adaptive size and
        shear (sigma, g1, g2) measured by HSM at grid x grid points from corner to corner of the CCD; the same
        for every object and chunk of the CCD, made once. None where the CCD has no PSF or HSM fails at a point."""
        key = (ccd_index, int(grid))
        if key not in self._moment_splines:
            from scipy.interpolate import RectBivariateSpline

            ny, nx = shape
            xs, ys = np.linspace(0.0, nx - 1.0, grid), np.linspace(0.0, ny - 1.0, grid)
            guess = self.sigma_guess(ccd_index, shape)
            vals = np.empty((3, grid, grid))
            made = guess is not None
            for i, yy in enumerate(ys):
                for j, xx in enumerate(xs):
                    got = self.at(ccd_index, xx, yy) if made else None
                    mom = psf_moments(got[0], guess) if got is not None else None
                    if mom is None:
                        made = False
                        break
                    vals[:, i, j] = mom[0], mom[1][0], mom[1][1]
            self._moment_splines[key] = tuple(RectBivariateSpline(ys, xs, v, kx=3, ky=3) for v in vals) \
                if made else None
        return self._moment_splines[key]

    def _model(self, ccd_index):
        return ccd_index if self.model_ccd is None else self.model_ccd[ccd_index]

    def model_uv(self, ccd_index, x, y):
        """The fitted model's field coordinates (u, v) of CCD pixels (x, y) (arrays), or None without a fitted
        model."""
        if self.fitted is None:
            return None
        if self._frame is None:
            self._frame = FieldFrame(**self.fitted.frame)
        ra, dec = pixel_to_sky(self.ccds[ccd_index].wcs, x, y)
        return self._frame.uv(ra, dec)

    def at(self, ccd_index, x, y, uv=None):
        """(PSF image, oversampling) at CCD pixel (x, y), or None where the model has no stars (or no PSF at all).
        ``uv``: the fitted model's (u, v) there, where already known (:meth:`model_uv`)."""
        if self.fitted is not None:
            m = self._model(ccd_index)
            if not self.fitted.ccd_used[m]:
                return None
            u, v = self.model_uv(ccd_index, x, y) if uv is None else uv
            return self.fitted.image(m, float(u), float(v)), self.fitted.oversampling
        if self.images is not None:
            return self.images[ccd_index]
        if self.psfex is not None:
            return self.psfex[ccd_index].image_at(x, y)
        return None   # an exposure left out: too few stars for a PSF model

    def fitted_at_many(self, ccd_index, x, y, uv):
        """The fitted model's PSF images (n, k n, k n), oversampling and registration shifts (n, 2) at CCD pixels
        (x, y) (arrays; ``uv`` their (u, v), :meth:`model_uv`), each as :meth:`at` and :meth:`shift` give it;
        None without a fitted model or where it has no stars on the CCD."""
        if self.fitted is None:
            return None
        m = self._model(ccd_index)
        if not self.fitted.ccd_used[m]:
            return None
        return (self.fitted.images_at(m, uv[0], uv[1]), self.fitted.oversampling,
                self.fitted.registration_shifts(m, x, y))

    def shift(self, ccd_index, x, y):
        """Astrometric registration offset (dx, dy) pixels at (x, y) (sec. 4); 0 for a given PSF."""
        if self.fitted is None:
            return 0.0, 0.0
        return self.fitted.registration_shift(self._model(ccd_index), x, y)


def _load_psf(spec, n_ccd, index, ccds=None, fit=None):
    """The exposure's PSF: the given file (FITS images, PSFEx, or a shearfit model), else ``fit()``.

    ``n_ccd`` is the number of CCD HDUs in the image file; ``ccds`` the CCDs read from it, of which
    those without a WCS may have been left out (their ``ccd_index`` says which PSF HDU is theirs).
    """
    positions = list(range(n_ccd)) if ccds is None else [c.ccd_index for c in ccds]
    if spec.psf is None:
        if fit is None:
            raise ShearfitValueError(f"exposure {index} ({spec.image}) has no psf and no stars to fit one")
        return _ExposurePSF(fitted=fit(), ccds=ccds)
    if is_psf_model_file(spec.psf):
        model = read_psf_model(spec.psf)
        if model.n_ccd != n_ccd:
            raise ShearfitValueError(f"{spec.psf}: PSF model of {model.n_ccd} CCDs, but {spec.image} has {n_ccd} "
                                     f"CCDs; the model must be of this exposure")
        return _ExposurePSF(fitted=model, ccds=ccds, model_ccd=None if positions == list(range(n_ccd)) else positions)
    if str(spec.psf).lower().endswith(".piff"):   # a Piff model: the optional piff package is imported only here
        from ..io.piffpsf import PiffModel

        model = PiffModel(spec.psf, n_ccd=n_ccd, headers={c.ccd_index: c.header for c in ccds or ()})
        return _ExposurePSF(psfex=[model.for_ccd(p) for p in positions])
    if str(spec.psf).endswith(".psf"):
        if n_ccd != 1:
            raise ShearfitValueError(f"{spec.psf}: a PSFEx .psf file describes one CCD, but {spec.image} has "
                                     f"{n_ccd}; give a FITS file with one PSF HDU per CCD")
        return _ExposurePSF(psfex=[PSFExModel(spec.psf)])
    idx = psf_image_hdus(spec.psf)
    if len(idx) != n_ccd:
        raise ShearfitValueError(f"{spec.psf} has {len(idx)} PSF image HDUs but {spec.image} has {n_ccd} CCDs; "
                                 f"a given PSF needs one image HDU per CCD, in the image's order")
    return _ExposurePSF(images=[_immutable(read_psf_fits(spec.psf, idx[p])) for p in positions])


def _immutable(got):
    """A given PSF (image, oversampling) with the image as a read-only array of its own, which the CCD's
    objects' Observations and the engine's transforms then share instead of copying."""
    img, k = got
    img = np.array(img, dtype=np.float64, copy=True)
    img.setflags(write=False)
    return img, k


def star_catalogue_positions(cfg: FieldConfig):
    """(ra, dec) of the field's star catalogue (``stars:``), or None without one."""
    if cfg.stars is None:
        return None
    stars = read_catalog(cfg.stars)
    return np.asarray(stars["ra"], float), np.asarray(stars["dec"], float)


def psf_star_positions(cfg: FieldConfig, cat, ccds, stars=None):
    """(ra, dec) of the PSF stars of one exposure: the star catalogue (``stars``: its
    :func:`star_catalogue_positions`, where already read), else the stellar locus of ``cat``."""
    if cfg.stars is not None:
        return star_catalogue_positions(cfg) if stars is None else stars
    rows = stellar_locus(ccds, cat, cfg.pipeline, FieldFrame.of_exposure(ccds))
    return np.asarray(cat["ra"], float)[rows], np.asarray(cat["dec"], float)[rows]


def fit_exposure_psf(cfg: FieldConfig, cat, ccds, label, stars=None):
    """Fit one exposure's pixel PSF model from its stars (sec. 5) (``stars``: the star catalogue's
    :func:`star_catalogue_positions`, where already read: it is read once for all the exposures)."""
    sra, sdec = psf_star_positions(cfg, cat, ccds, stars)
    ora = np.concatenate([np.asarray(cat["ra"], float), sra])
    odec = np.concatenate([np.asarray(cat["dec"], float), sdec])
    res = build_exposure_psf(ccds, sra, sdec, ora, odec, cfg.pipeline, label=label)
    for note in res.notes:
        log.warning(note)
    return res


def _psf_fwhm_pixels(moments, k):
    # Gaussian-equivalent FWHM from the adaptive sigma; a typical ground-based PSF if HSM failed
    return 2.3548 * moments[0] / k if moments is not None else 3.5


@functools.lru_cache(maxsize=8)
def _centred_offsets(shape):
    """Pixel offsets (dx, dy) from the centre pixel ``(ny // 2, nx // 2)`` of a stamp of ``shape``."""
    ny, nx = shape
    yy, xx = np.indices(shape)
    return xx - nx // 2, yy - ny // 2


def _nearest_map(A, shape, use_kernel=True):
    """Where each pixel of a stamp lands on another stamp of the same shape under the linear map ``A``.

    Offsets from the centre pixel are mapped by ``A`` and rounded to the nearest pixel (no
    interpolation). Returns the flat indices into the other stamp and a mask of the pixels that
    land inside it; None where every pixel lands on itself (the grids are aligned to well under half
    a pixel across the stamp, as for dithered exposures of one camera orientation).
    """
    return _map_of(_floats(A), shape, use_kernel)


def _map_of(m, shape, use_kernel=True):
    """:func:`_nearest_map` of the matrix given as its :func:`_floats`."""
    ny, nx = shape
    a, b, c, d = m
    # (np.abs(A - I).max() in Python floats, without its overhead; a NaN, which max may pass over, is no identity)
    if max(abs(a - 1.0), abs(b), abs(c), abs(d - 1.0)) * (nx + ny) < 1.0 and a == a and b == b and c == c and d == d:
        return None
    if use_kernel and USE_KERNEL:
        # (the compiled kernel: the same arrays in one pass)
        index, inside = np.empty(shape, np.int64), np.empty(shape, bool)
        KERNEL.nearest_map(np.array((a, b, c, d)), int(ny), int(nx), index, inside.view(np.uint8))
        return index, inside
    dx, dy = _centred_offsets(shape)
    px = np.rint(a * dx + b * dy).astype(np.int64) + nx // 2
    py = np.rint(c * dx + d * dy).astype(np.int64) + ny // 2
    inside = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)
    return np.where(inside, py * nx + px, 0), inside


def _floats(J):
    """A 2 x 2 matrix as the Python floats ``(a, b, c, d)`` of its rows."""
    (a, b), (c, d) = np.asarray(J, float).tolist()
    return a, b, c, d


def _product(m, n):
    """The 2 x 2 product ``m n`` of two :func:`_floats` matrices, in Python floats (each element two products
    and a sum, the same on every CPU: numpy's ``@`` calls a BLAS whose fused multiply-adds depend on it)."""
    a, b, c, d = m
    e, f, g, h = n
    return a * e + b * g, a * f + b * h, c * e + d * g, c * f + d * h


def _inverse(m):
    """The inverse of a :func:`_floats` matrix by its adjugate, or None where it is singular or not finite."""
    a, b, c, d = m
    det = a * d - b * c
    if not (det != 0.0 and math.isfinite(det)):
        return None
    return d / det, -b / det, -c / det, a / det


def _reference_maps(cuts, shape):
    """For each stamp of an object: the nearest-pixel maps from the first stamp's grid (the reference) onto it and
    back (:func:`_nearest_map`; None where the grids agree), and where its object lands on the reference grid.

    ``A = J^-1 J0`` takes reference-pixel offsets to this exposure's, ``B = A^-1`` back. In Python floats for the
    usual, invertible Jacobians; numpy's matrices (which may carry infinities or NaNs) otherwise."""
    J0 = _floats(cuts[0]["J"])
    to_ref, from_ref, offsets = [], [], []
    for c in cuts:
        Ji = _inverse(_floats(c["J"]))
        A = _product(Ji, J0) if Ji is not None else None
        B = _inverse(A) if A is not None else None
        if B is None:
            A = inv2(c["J"]) @ cuts[0]["J"]
            B = inv2(A)
            off = tuple((B @ np.asarray(c["offset"], float)).tolist())
            A, B = _floats(A), _floats(B)
        else:
            ox, oy = (float(v) for v in c["offset"])
            off = (B[0] * ox + B[1] * oy, B[2] * ox + B[3] * oy)
        to_ref.append(_map_of(A, shape))
        from_ref.append(_map_of(B, shape))
        offsets.append(off)
    return to_ref, from_ref, offsets


def _isophote_analysis(cuts, pc, near=()) -> int:
    """Sec. 3.6 on the co-added, smoothed stamp: neighbour masks, dropped exposures, blend/centroid flags.

    The co-add is built on the first exposure's pixel grid, every other stamp carried onto it to
    the nearest pixel (never interpolated). For exposures on the same grid, as the paper's were,
    that is the stamps as cut; a rotated, flipped or differently distorted exposure is carried
    through its local Jacobian (a reference pixel takes the value and weight of the exposure's
    pixel nearest to the same sky position; where the exposure has none, weight 0). Neighbour
    masks and the isophote go back to each exposure the same way, so every exposure gets its
    neighbours masked and its bad pixels judged against the same isophote.

    ``near`` holds the other catalogue objects around this one, ``(index, exposure, CCD, x, y)`` for
    each CCD they lie on (:func:`catalogue_neighbours`): one whose position, carried onto the
    reference grid from the first of the object's stamps it lies on, falls inside the isophote makes
    the object blended (-3), where the deblender found a single maximum.
    """
    J0 = cuts[0]["J"]
    to_ref, from_ref, offsets = _reference_maps(cuts, cuts[0]["image"].shape)
    fwhm = float(np.mean([_psf_fwhm_pixels(c["moments"], c["k"]) for c in cuts]))
    res = analyse_stamps([c["image"] for c in cuts], [c["weight"] for c in cuts], offsets, fwhm,
                         nsigma=pc.isophote_nsigma, min_region_pixels=pc.deblend_min_pixels,
                         centroid_max_shift=pc.isophote_centroid_max_shift, neighbour_mask=pc.neighbour_mask,
                         carry=to_ref)
    any_isophote = bool(res.isophote.any())
    if res.flag == 0 and len(near) and any_isophote and _neighbour_inside(cuts, near, res.isophote, offsets, J0):
        return FITCLASS_BLENDED
    iso = res.isophote.ravel()
    for c, mask, keep, m in zip(cuts, res.masks, res.keep_exposure, from_ref):
        if m is not None and any_isophote:
            # a bad pixel of this exposure's own stamp inside the isophote drops it (reference pixels
            # beyond a rotated stamp's corners hold no data from it, but are not its bad pixels): the
            # stamp's few bad pixels looked up on the isophote carried onto it
            badpix = np.flatnonzero(c["weight"] <= 0)
            keep = not bool((m[1].ravel()[badpix] & iso[m[0].ravel()[badpix]]).any())
        c["keep"] = True
        if pc.neighbour_mask and mask is not None and mask.any():
            c["weight"] = np.where(carry_stamp(mask, m), 0.0, c["weight"])
        if pc.drop_masked_exposures and not keep:
            c["keep"] = False
    return int(res.flag)


def _neighbour_inside(cuts, near, isophote, offsets, J0) -> bool:
    """Whether a catalogue neighbour's position lands on a pixel of ``isophote`` (the reference grid of
    :func:`_isophote_analysis`): its offset from the object on the first stamp's CCD it shares, carried onto the
    reference grid through the two exposures' local Jacobians and rounded to the nearest pixel."""
    ny, nx = isophote.shape
    J0inv = _inverse(_floats(J0))
    seen = set()
    for c, off in zip(cuts, offsets):
        B = None
        for j, e, ccd, x, y in near:
            if j in seen or e != c["e"] or ccd != c["c"]:
                continue
            seen.add(j)
            if B is None:   # this exposure's pixel offsets -> the reference grid's (a singular J0: numpy's NaNs)
                B = _product(J0inv, _floats(c["J"])) if J0inv is not None else _floats(inv2(J0) @ c["J"])
            dx, dy = float(x - c["x"]), float(y - c["y"])
            px, py = B[0] * dx + B[1] * dy + off[0], B[2] * dx + B[3] * dy + off[1]
            if not (math.isfinite(px) and math.isfinite(py)):
                continue
            ix, iy = round(px) + nx // 2, round(py) + ny // 2
            if 0 <= ix < nx and 0 <= iy < ny and isophote[iy, ix]:
                return True
    return False


def catalogue_neighbours(hits, n_objects, radius):
    """Each object's catalogue neighbours: the objects within ``radius`` pixels of it on a CCD they share.

    ``hits`` are :func:`shearfit.io.stamps.locate_all`'s locations of the whole catalogue (not one chunk's, so
    that a neighbour measured in another chunk counts). Returns ``(ptr, idx)``: object ``i``'s neighbours are
    ``idx[ptr[i]:ptr[i + 1]]`` (sorted, each once), from one k-d tree per CCD."""
    from scipy.spatial import cKDTree

    pairs = [np.empty((0, 2), np.int64)]
    obj = np.asarray(hits.object, np.int64)
    order = np.argsort(hits.ccd, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(np.asarray(hits.ccd)[order]) != 0, True])
    for a, b in zip(starts[:-1], starts[1:]):   # the hits of one CCD: order[a:b]
        if b - a < 2:
            continue
        sel = order[a:b]
        got = cKDTree(np.c_[hits.x[sel], hits.y[sel]]).query_pairs(radius, output_type="ndarray")
        pairs.append(obj[sel][got])
    pairs = np.concatenate(pairs)
    pairs = np.unique(np.concatenate([pairs, pairs[:, ::-1]]), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]          # a duplicate catalogue row is another object
    ptr = np.searchsorted(pairs[:, 0], np.arange(n_objects + 1))
    return ptr, pairs[:, 1].copy()


def _near_hits(near, tasks, idx):
    """For each object of ``idx``: its catalogue neighbours' ``(index, exposure, CCD, x, y)`` on every CCD they
    lie on (empty without ``near``)."""
    if near is None:
        return [()] * len(idx)
    ptr, nb = near
    return [[(int(j),) + t for j in nb[ptr[i]:ptr[i + 1]] for t in tasks[j]] for i in idx]


def measure_field(cfg: FieldConfig, out_path=None, progress=False, processes=1, restart=False, scheduler=None,
                  executor="dask", memory_limit="auto") -> Table:
    """Measure every catalogue object on the field's exposures; write and return the catalogue.

    Objects are measured in chunks of ``chunk_size`` neighbouring objects;
    finished chunks are kept in ``OUTPUT.parts/`` (see :class:`Checkpoint`),
    so rerunning after an interruption resumes, and the final catalogue is
    the same as an uninterrupted run's. ``restart`` discards a checkpoint.

    Chunks run on Dask: on ``processes`` workers of a local cluster, or on
    the distributed scheduler at ``scheduler`` (its workers must see the
    same files); ``executor="processes"`` (or its old name ``"fork"``) uses a plain process pool instead
    (:mod:`shearfit.workers`). The
    catalogue does not depend on either. ``memory_limit`` is the local
    cluster's per worker (Dask's format: ``"2GB"``, bytes, or ``"auto"``).

    The run holds this process's BLAS to one thread (:func:`shearfit.workers.single_threaded`, restored
    after), as each worker's is: the star fits' and the engine's small matrix products take more CPU time
    on several threads and no less wall time.
    """
    with single_threaded():
        return _measure_field(cfg, out_path, progress, processes, restart, scheduler, executor, memory_limit)


def _measure_field(cfg, out_path, progress, processes, restart, scheduler, executor, memory_limit):
    out_path = out_path or cfg.output
    if out_path is None:
        raise ShearfitValueError("no output path: give --out or output: in the config")
    if (cfg.calibration == "metacal" and cfg.pipeline.metacal_replay and cfg.pipeline.metacal_own_grid
            and cfg.fit.sampling != "adaptive"):
        raise ShearfitValueError(f"{cfg.source}: setting metacal_own_grid needs sampling: adaptive "
                                 f"(the config has sampling: {cfg.fit.sampling})")
    out_dir = os.path.dirname(os.path.abspath(out_path))
    if not os.path.isdir(out_dir) or not os.access(out_dir, os.W_OK):
        raise ShearfitValueError(f"cannot write the output: directory {out_dir} does not exist or is not writable")
    # a bad calibration file fails here, not after every object is measured
    calibration = load_calibration(cfg.calibration) if cfg.calibration not in CALIBRATION_MODES else None
    # a duplicate id stops the run here, before any work; a row without a finite position or magnitude only
    # costs itself (fitclass -7)
    cat = read_catalog(cfg.catalog, strict=False)
    bad = _bad_catalogue_rows(cat, cfg.catalog)
    good = np.flatnonzero(~bad)
    exposures = _read_exposures(cfg, cat[good])
    flat = [(e, c) for e, (ccds, _) in enumerate(exposures) for c in range(len(ccds))]
    ra = np.where(bad, np.nan, np.asarray(cat["ra"], float))
    dec = np.where(bad, np.nan, np.asarray(cat["dec"], float))
    hits = locate_all([exposures[e][0][c] for e, c in flat], ra, dec)
    # from here on the pixels are opened per chunk (memory-mapped), by whichever process measures it, and
    # the pages the objects read are released every few objects: memory does not grow with the field or the run
    exposures = _detached_exposures(exposures)
    metacal = cfg.calibration == "metacal"
    table = empty_output_table(cat, metacal=metacal)
    for name in table.colnames:
        if name == "fitclass" or name.startswith("fitclass_"):
            table[name][bad] = FITCLASS_BAD_INPUT
    tasks = [[] for _ in range(len(cat))]
    for obj, k, x, y in zip(hits.object, hits.ccd, hits.x, hits.y):
        tasks[obj].append((flat[k][0], flat[k][1], float(x), float(y)))
    mags = np.asarray(cat["mag"], float)
    near = None
    if cfg.pipeline.catalogue_blends:
        # the neighbours on the first stamp (within its half-diagonal): a pair the deblender cannot split lies a
        # few pixels apart; one further away inside a larger object's isophote shows its own maximum
        near = catalogue_neighbours(hits, len(cat), cfg.pipeline.stamp_size / np.sqrt(2.0) + 1.0)
    # the bad rows are in no chunk: they are not measured
    chunks = [good[c] for c in sky_chunks(cat[good], cfg.pipeline.chunk_size)]
    ckpt = Checkpoint(out_path, cfg, cat, len(chunks), restart=restart)
    for k in ckpt.finished():
        ckpt.load(k, table)
    todo = [k for k in range(len(chunks)) if not ckpt.is_done(k)]
    if todo and len(todo) < len(chunks):
        log.info("resuming: %d of %d chunks already measured (%s)", len(chunks) - len(todo), len(chunks), ckpt.dir)
    global _STATE
    ids = np.asarray(cat["id"])
    _STATE = (tasks, exposures, mags, cfg, chunks, ids, near)
    bar = _progress_bar(sum(len(chunks[k]) for k in todo), progress)
    try:
        if todo and (scheduler is not None or (processes and processes > 1 and executor == "dask")):
            _run_dask(cfg, exposures, tasks, mags, ids, chunks, todo, table, ckpt, bar, processes, scheduler,
                      memory_limit, near)
        elif processes and processes > 1 and len(todo) > 1:
            # the workers get the field's state once (inherited with fork, pickled with spawn); each returns
            # one chunk's rows, which the parent writes to the checkpoint as they come (a kill loses at most
            # the chunks in flight)
            with process_pool(processes, initializer=_set_state, initargs=(_STATE,)) as pool:
                for k, rows in pool.imap_unordered(_measure_chunk, todo):
                    _store_chunk(table, chunks[k], rows, ckpt, k, bar)
        else:
            for k in todo:
                _store_chunk(table, chunks[k], _measure_chunk(k)[1], ckpt, k, bar)
    finally:
        _STATE = None
        if bar is not None:
            bar.close()
    measured = np.asarray(table["fitclass"]) >= 0
    # lensfit's weight responds to shear where likelihoods are broad (small galaxies): the catalogue also
    # carries each galaxy's bin mean of it, which does not (shearfit.calib.weights)
    nb = isotropic_bins(int(np.count_nonzero(np.asarray(table["fitclass"]) == FITCLASS_GALAXY)))
    table["iso_weight"] = isotropic_weights(table, nb)
    cards = list(provenance_cards(cfg.to_dict(), __version__))
    cards += [("ISOBINS", nb, "iso_weight: bins of flux_snr")]
    if metacal:
        # the response is measured per galaxy (R11 .. R22): no simulation-based m
        table["m"] = np.where(measured, 0.0, np.nan)
        cards += [("CALMODE", "metacal", "shear response: metacal (R columns)"),
                  ("MCDELTA", cfg.pipeline.metacal_delta, "metacal shear step"),
                  ("MCPSF", cfg.pipeline.metacal_psf, "metacal new PSF: dilated or round"),
                  ("MCREPLAY", bool(cfg.pipeline.metacal_replay), "metacal versions replay the noshear fit"),
                  ("MCOWNGRD", bool(cfg.pipeline.metacal_replay and cfg.pipeline.metacal_own_grid),
                   "metacal replays run their own ellipticity grid"),
                  ("MCOWNPOS", bool(cfg.pipeline.metacal_replay and cfg.pipeline.metacal_own_position),
                   "metacal replays find their own position")]
    elif calibration is None and cfg.fit.noise_bias_correction:
        # the estimates are corrected for their noise bias by extrapolation: no simulation table was fitted so
        table["m"] = np.where(measured, 0.0, np.nan)
        mode = "noise bias on the model" if cfg.fit.noise_bias_on_model else "noise-bias extrapolation"
        cards += [("CALMODE", mode, "e corrected by noise_bias_correction; m 0")]
    else:
        if calibration is not None:
            src = os.path.basename(cfg.calibration)
        else:
            selfcal = bool(cfg.fit.self_calibration)
            calibration = default_calibration(self_calibration=selfcal)
            src = "shearfit default, self-cal" if selfcal else "shearfit default"
        alpha, beta = calibration.alpha, calibration.beta
        table["m"] = np.where(measured, calibration.m(table["snr"], table["scalelength"], table["psf_fwhm"]), np.nan)
        cards += [("CALMODE", "simulations", "m(snr, size) from simulations"),
                  ("CALMODEL", calibration.kind, "m from the bins' table or the paper's form"),
                  ("CALSIZE", calibration.size, "m table size axis: scalelength or resolution"),
                  ("CALALPHA", alpha, f"calibration alpha ({src})"), ("CALBETA", beta, f"calibration beta ({src})")]
    write_catalog_atomic(table, out_path, cards)
    ckpt.remove()
    return table


def _bad_catalogue_rows(cat, path):
    """Rows of the catalogue that cannot be measured (non-finite ra, dec or mag; dec beyond the poles), logged."""
    bad = np.zeros(len(cat), bool)
    for name, rows in bad_rows(cat).items():
        if rows.size:
            bad[rows] = True
            what = "not finite or outside [-90, 90]" if name == "dec" else "not finite"
            shown = ", ".join(str(r) for r in rows[:10]) + (", ..." if rows.size > 10 else "")
            log.warning("%s: column %r is %s (NaN, inf or masked) in %d rows (%s); those rows are not measured "
                        "(fitclass %d)", path, name, what, rows.size, shown, FITCLASS_BAD_INPUT)
    return bad


def _read_exposures(cfg: FieldConfig, cat):
    """Every exposure's CCDs and PSF, leaving out, with a warning, what cannot be used.

    A CCD without a usable WCS is left out (:func:`read_exposure`); one without a usable pixel is kept but
    marked (its objects are measured on the other exposures); an exposure whose stars are too few for a PSF
    model keeps its CCDs with no PSF (the same). Given PSF files are all read and checked against their
    exposures before any PSF is fitted, so that a mismatch stops the run before that work.
    """
    read = []
    for k, spec in enumerate(cfg.exposures):
        ccds = read_exposure(spec.image, spec.weight, skip_unusable=True)
        if not ccds:
            log.warning("%s: no CCD with a usable WCS; exposure %d is left out", spec.image, k)
            continue
        given = _load_psf(spec, ccds[0].n_file_ccds, k, ccds=ccds) if spec.psf is not None else None
        read.append((k, spec, ccds, given))
    exposures = []
    stars = functools.lru_cache(maxsize=1)(lambda: star_catalogue_positions(cfg))   # read once, if needed
    for k, spec, ccds, psf in read:
        if psf is None:
            hdus = ", ".join(str(c.hdu) for c in ccds)
            if not any(c.usable for c in ccds):
                log.warning("exposure %d (%s, HDU %s): no CCD has a usable pixel; the exposure is left out",
                            k, spec.image, hdus)
                psf = _ExposurePSF(ccds=ccds)
            else:
                fit = functools.partial(_fitted_psf, cfg, cat, ccds, f"exposure {k} ({spec.image})", stars)
                try:
                    psf = _load_psf(spec, ccds[0].n_file_ccds, k, ccds=ccds, fit=fit)
                except TooFewStarsError as exc:
                    log.warning("%s; the exposure is left out (%s, HDU %s)", exc, spec.image, hdus)
                    psf = _ExposurePSF(ccds=ccds)   # no PSF anywhere: its objects are measured on the others
        exposures.append((ccds, psf))
    return exposures


def _fitted_psf(cfg, cat, ccds, name, stars):
    """The PSF model fitted from the stars of one exposure (called only where no PSF is given); ``stars``: a
    callable that gives the star catalogue's positions (read on the first call)."""
    return fit_exposure_psf(cfg, cat, ccds, name, stars()).model


def sky_chunks(cat, size):
    """Catalogue indices in chunks of ``size`` neighbouring objects (cells of 2 arcmin, then input order).

    Deterministic: the same catalogue and size give the same chunks, so a
    resumed run and an uninterrupted one measure the same objects per chunk;
    the results do not depend on the chunking anyway (each object is fitted
    on its own).
    """
    ra = np.asarray(cat["ra"], float)
    dec = np.asarray(cat["dec"], float)
    n = ra.size
    if n == 0:
        return []
    cell = 2.0 / 60.0
    cosd = np.cos(np.radians(np.median(dec)))
    ra_c = ((ra - np.median(ra) + 180.0) % 360.0) * cosd
    order = np.lexsort((np.arange(n), np.floor(ra_c / cell), np.floor(dec / cell)))
    return [order[i:i + size] for i in range(0, n, size)]


def _progress_bar(total, show):
    if not show or total == 0:
        return None
    from tqdm import tqdm
    return tqdm(total=total, desc="measuring", unit="obj")


def _detached_exposures(exposures):
    """The exposures with their CCDs' pixels dropped (WCS, keywords and PSF models kept)."""
    out = []
    for ccds, p in exposures:
        meta = detached(ccds)
        out.append((meta, p if p.ccds is None else replace(p, ccds=meta)))
    return out


def _attached(exposures):
    """The exposures with their pixels memory-mapped and their WCS read again, for one chunk."""
    out = []
    for ccds, p in exposures:
        ccds = attach_pixels(ccds)
        out.append((ccds, p if p.ccds is None else replace(p, ccds=ccds)))
    return out


def _measure_objects(exposures, hits, mags, ids, cfg, near=None):
    """One chunk's objects: the exposures' memory maps opened once, the pages the objects read released every
    :data:`RELEASE_EVERY` objects and at the end (an object touches about 5 MB of pages on 7 exposures; kept, a
    chunk's would add up; released after every object, the next one, often on the same rows, reads them again).
    ``near``: each object's catalogue neighbours (:func:`_near_hits`), or None."""
    hits = list(hits)
    near = [()] * len(hits) if near is None else near
    opened = _attached(exposures)
    geometry = _chunk_geometry(opened, hits, cfg.pipeline.psf_moment_grid)
    rows = []
    for n, (h, m, i) in enumerate(zip(hits, mags, ids)):
        rows.append(_measure_one(h, opened, m, cfg, cfg.pipeline, i, geometry, near[n]))
        if (n + 1) % RELEASE_EVERY == 0 or n + 1 == len(hits):
            for ccds, _ in opened:
                release_pages(ccds)
    return rows


#: Objects measured between releases of the exposures' memory-mapped pages (:func:`shearfit.io.fits.release_pages`).
RELEASE_EVERY = 8


def _chunk_geometry(exposures, hits, moment_grid=0) -> dict:
    """At every (exposure, CCD, x, y) the chunk's objects fall on, keyed so: (the local WCS Jacobian, the fitted
    PSF model's (u, v), its (PSF image, oversampling), its registration shift (dx, dy) and the PSF's adaptive
    moments from the CCD's grid (:meth:`_ExposurePSF.moments_many`); (u, v), image and shift None without a
    fitted model, the moments None without a grid), from one vectorised :func:`local_jacobian`, one sky
    conversion, one product of the model's terms with its images and one evaluation of the moments' splines per
    CCD instead of one call per object and exposure (the same numbers, to rounding)."""
    where = {}
    for obj in hits:
        for e, c, x, y in obj:
            where.setdefault((e, c), set()).add((x, y))
    out = {}
    for (e, c), pts in where.items():
        pts = sorted(pts)
        xy = np.array(pts, float)
        J = local_jacobian(exposures[e][0][c].wcs, xy[:, 0], xy[:, 1])
        epsf = exposures[e][1]
        uv = epsf.model_uv(c, xy[:, 0], xy[:, 1])
        batch = None
        if uv is not None:
            batch = epsf.fitted_at_many(c, xy[:, 0], xy[:, 1], uv)
        moments = epsf.moments_many(c, exposures[e][0][c].shape, xy[:, 0], xy[:, 1], moment_grid) \
            if moment_grid else None
        for n, (x, y) in enumerate(pts):
            got, shift = (None, None) if batch is None else ((batch[0][n], batch[1]), tuple(batch[2][n].tolist()))
            out[(e, c, x, y)] = (J[n], None if uv is None else (uv[0][n], uv[1][n]), got, shift,
                                 None if moments is None else moments[n])
    return out


def _set_state(state):
    """Worker initializer: the field's state for :func:`_measure_chunk`."""
    global _STATE
    _STATE = state


def _measure_chunk(k):
    tasks, exposures, mags, cfg, chunks, ids, near = _STATE
    idx = chunks[k]
    return k, _measure_objects(exposures, [tasks[i] for i in idx], mags[idx], ids[idx], cfg,
                               _near_hits(near, tasks, idx))


def _dask_chunk(run, k, hits, mags, ids, near=None):
    """One chunk on a Dask worker: its objects' pixels read through memory maps opened for this chunk."""
    cfg, exposures = run
    return k, _measure_objects(exposures, hits, mags, ids, cfg, near)


def local_cluster_config() -> dict:
    """The Dask settings of the local cluster that ``shearfit measure -j N`` starts (for ``dask.config.set``).

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (``distributed.nanny.pre-spawn-environ``), so
    that they hand freed memory back to the system at once; glibc then also stops raising its mmap threshold, and
    the fits' temporary arrays are mapped and unmapped again and again. Here the workers start without it, as a
    process pool's do (the pipeline bounds its memory itself: pages released every few objects, chunks of
    ``chunk_size``), with one BLAS thread each, and without Dask's sampling profiler, whose thread takes the GIL from
    the fits every 10 ms. Before this and the PSF images' fix (``_ExposurePSF.__setstate__``) a chunk of 256
    objects took about 260 000 page faults in a Dask worker, against some 6000 in a process pool's
    (``benchmarks/pipeline_workers.py --before``; ``benchmarks/README.md``, session
    86). Workers of a cluster of your own (``--scheduler``) are started by you: give them the same settings.
    """
    import dask
    import distributed  # noqa: F401  (registers distributed's defaults with dask.config)

    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    environ.update(SINGLE_THREAD_ENV)
    return {"distributed.nanny.pre-spawn-environ": environ, "distributed.worker.profile.enabled": False}


def _run_dask(cfg, exposures, tasks, mags, ids, chunks, todo, table, ckpt, bar, processes, scheduler,
              memory_limit="auto", near=None):
    """Submit the chunks to Dask and checkpoint each as it completes."""
    import dask
    from dask.distributed import Client, LocalCluster, as_completed

    # Dask's own progress messages are not the user's business at the default verbosity
    logging.getLogger("distributed").setLevel(max(logging.WARNING, log.getEffectiveLevel()))
    cluster = None
    if scheduler is None:
        try:
            with dask.config.set(local_cluster_config()):
                cluster = LocalCluster(n_workers=int(processes), threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.WARNING, memory_limit=memory_limit)
        except (ValueError, TypeError) as exc:
            raise ShearfitValueError(f"--memory-limit {memory_limit!r}: {exc}") from None
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise ShearfitValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    try:
        # one copy of the run's settings, CCD metadata and PSF models per worker (a list of one: scatter sends
        # it whole); the PSF models' caches are rebuilt there
        portable = [(ccds, replace(p, _frame=None, _moffat={}, _moment_splines={})) for ccds, p in exposures]
        [run] = client.scatter([(cfg, portable)], broadcast=True)
        futures = [client.submit(_dask_chunk, run, k, [tasks[i] for i in chunks[k]], mags[chunks[k]], ids[chunks[k]],
                                 _near_hits(near, tasks, chunks[k]), pure=False) for k in todo]
        for fut in as_completed(futures):
            k, rows = fut.result()
            _store_chunk(table, chunks[k], rows, ckpt, k, bar)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _store_chunk(table, idx, rows, ckpt, k, bar):
    versions = [c for c in table.colnames if c.startswith("fitclass_")]   # a metacal catalogue's
    for i, row in zip(idx, rows):
        for key, val in row.items():
            table[key][i] = val
        if versions and "fitclass" in row and versions[0] not in row:
            # an object the pipeline stopped before its fits (blended, too few exposures, ...): every version
            # carries its flag
            for c in versions:
                table[c][i] = row["fitclass"]
    ckpt.save(k, table, idx)
    if bar is not None:
        bar.update(len(idx))


class Checkpoint:
    """Finished chunks of a run, kept beside its output in ``OUTPUT.parts/`` until the catalogue is written.

    ``manifest.yaml`` identifies the run (software version, the resolved
    configuration, the catalogue's ids and positions, the number of chunks);
    each ``chunk_NNNNNN.fits`` holds the measured rows of one chunk and is
    written atomically, so a kill leaves whole chunks or none. A rerun of the
    same command loads them instead of measuring again; a checkpoint of a
    different run is refused (``--restart`` discards it).
    """

    def __init__(self, out_path, cfg, cat, n_chunks, restart=False):
        self.dir = os.fspath(out_path) + ".parts"
        h = hashlib.sha256()
        h.update(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode())
        for col in ("id", "ra", "dec", "mag"):
            h.update(np.ascontiguousarray(np.asarray(cat[col])).tobytes())
        self.manifest = {"shearfit_version": __version__, "run": h.hexdigest(), "n_objects": len(cat),
                         "n_chunks": int(n_chunks)}
        mpath = os.path.join(self.dir, "manifest.yaml")
        if restart and os.path.isdir(self.dir):
            shutil.rmtree(self.dir)
        if os.path.isdir(self.dir):
            try:
                with open(mpath) as f:
                    old = yaml.safe_load(f)
            except (OSError, yaml.YAMLError):
                old = None
            if old != self.manifest:
                raise ShearfitValueError(f"{self.dir}: a checkpoint of a different run (configuration, catalogue, "
                                         "chunk size or version changed); remove it or rerun with --restart")
        self._mpath = mpath
        self._done = {k for k in range(n_chunks) if os.path.exists(self._path(k))}

    def _path(self, k):
        return os.path.join(self.dir, f"chunk_{k:06d}.fits")

    def finished(self):
        return sorted(self._done)

    def is_done(self, k):
        return k in self._done

    def save(self, k, table, idx):
        try:
            if not os.path.isdir(self.dir):   # created with the first finished chunk: a run that fails first leaves nothing
                os.makedirs(self.dir)
                with atomic_path(self._mpath) as tmp, open(tmp, "w") as f:
                    yaml.safe_dump(self.manifest, f)
            part = table[idx]
            part["row"] = np.asarray(idx, np.int64)
            with atomic_path(self._path(k)) as tmp:
                part.write(tmp, format="fits")
        except OSError as exc:
            raise ShearfitIOError(f"{self._path(k)}: cannot write the checkpoint: {exc.strerror or exc}") from None
        self._done.add(k)

    def load(self, k, table):
        try:
            part = Table.read(self._path(k), format="fits")
        except (OSError, ValueError) as exc:
            raise ShearfitValueError(f"{self._path(k)}: unreadable checkpoint chunk ({exc}); remove it or rerun "
                                     "with --restart") from None
        idx = np.asarray(part["row"], np.int64)
        for col in table.colnames:
            if col in part.colnames:
                table[col][idx] = part[col]

    def remove(self):
        shutil.rmtree(self.dir, ignore_errors=True)


_STATE = None


_U64 = (1 << 64) - 1


#: the stamp sides an object too large for its stamp is measured again on (up to max_stamp_size)
LARGER_STAMPS = (64, 96, 128, 192, 256)


def stamp_ladder(pc) -> list:
    """The stamp sides an object is measured on in turn: ``stamp_size``, then the larger of
    :data:`LARGER_STAMPS` up to ``max_stamp_size``, while its truncated model is too large (fitclass -4)."""
    return [pc.stamp_size] + [s for s in LARGER_STAMPS if pc.stamp_size < s <= pc.max_stamp_size]


def _measure_one(hits, exposures, mag, cfg, pc, obj_id=0, geometry=None, near=()) -> dict:
    """One object's catalogue row: measured on stamps of ``stamp_size``, and again on larger ones while its
    truncated model does not fit (sec. 3.6: a Fourier model wraps around a stamp smaller than it). A size
    whose fit would need more than ``max_object_memory_mb`` is not measured: the object gets fitclass -8
    there (also where a smaller stamp was too small), with ``stamp_size`` that size. ``near``: the catalogue
    neighbours' locations (:func:`_isophote_analysis`)."""
    if not hits:
        return {"fitclass": FITCLASS_OFF_EXPOSURES}
    for size in stamp_ladder(pc):
        row = _measure_on_stamps(hits, exposures, mag, cfg, pc, obj_id, size, geometry, near)
        if row.get("fitclass") != FITCLASS_TOO_LARGE:
            break
    row.setdefault("stamp_size", size)
    return row


_MIB = 2.0 ** 20


def object_memory_bytes(cuts, size, cfg) -> float:
    """The estimated memory of an object's fit on its stamps ``cuts`` of side ``size``
    (:func:`shearfit.pipeline.memory.fit_memory_bytes`, each exposure's PSF FWHM from its adaptive moments)."""
    fwhm = [np.nan if c["moments"] is None else 2.3548 * c["moments"][0] / c["k"] for c in cuts]
    return fit_memory_bytes(size, len(cuts), cfg.fit, psf_fwhm=fwhm, psf_oversampling=[c["k"] for c in cuts],
                            metacal=cfg.calibration == "metacal")


def _measure_on_stamps(hits, exposures, mag, cfg, pc, obj_id, size, geometry=None, near=()) -> dict:
    # one stamp per exposure: where dithers put an object on two CCDs of one exposure, the CCD
    # where it lies furthest from the edge
    best = {}
    for e, c, x, y in hits:
        if not exposures[e][0][c].usable:   # a CCD without a usable pixel, left out with a warning
            continue
        ny, nx = exposures[e][0][c].shape
        margin = min(x, y, nx - 1 - x, ny - 1 - y)
        if e not in best or margin > best[e][0]:
            best[e] = (margin, c, x, y)
    cuts = []
    for e, (margin, c, x, y) in sorted(best.items()):
        ccd = exposures[e][0][c]
        epsf = exposures[e][1]
        J, uv, got, shift, mom = (None,) * 5 if geometry is None else geometry.get((e, c, x, y), (None,) * 5)
        if got is None:
            got = epsf.at(c, x, y, uv=uv)
        if got is None:   # a CCD without enough PSF stars
            continue
        psf, k = got
        # where the stars say the WCS is off, the object is where they put it (registration, sec. 4)
        dx, dy = epsf.shift(c, x, y) if shift is None else shift
        st = cut_stamp(ccd.image, ccd.pixel_weight, x + dx, y + dy, size)
        if st is None:
            continue
        # (cut_stamp's own new float64 arrays, made read-only so that the Observation shares them instead of copying)
        st.image.setflags(write=False)
        st.weight.setflags(write=False)
        cuts.append(dict(e=e, c=c, x=x, y=y, ccd=ccd, image=st.image, weight=st.weight,
                         offset=st.offset, J=local_jacobian(ccd.wcs, x, y) if J is None else J, psf=psf, k=k,
                         moments=mom if mom is not None else epsf.moments_at(c, ccd.image.shape, x, y, psf,
                                                                               pc.psf_moment_grid),
                         moffat=epsf.moffat(c, ccd.image.shape) if k == 1 else None))
    if not cuts:
        return {"fitclass": FITCLASS_FEW_EXPOSURES, "n_exposures_used": 0, "stamp_size": 0}
    if pc.max_object_memory_mb > 0:
        need = object_memory_bytes(cuts, size, cfg)
        if need > pc.max_object_memory_mb * _MIB:
            log.info("object %s: its fit on %d-pixel stamps of %d exposures would need about %.0f MiB, more than "
                     "max_object_memory_mb=%g; not measured (fitclass %d)", obj_id, size, len(cuts), need / _MIB,
                     pc.max_object_memory_mb, FITCLASS_MEMORY)
            return {"fitclass": FITCLASS_MEMORY, "n_exposures_used": 0, "weight": 0.0}
    flag = _isophote_analysis(cuts, pc, near)
    if flag != 0:
        return {"fitclass": flag, "n_exposures_used": 0}
    obs, psf_stats = [], []   # per exposure used: the PSF's ellipticity (e1, e2) and FWHM at the object
    for cut in cuts:
        if not cut["keep"]:
            continue
        try:
            obs.append(Observation(image=cut["image"], weight=cut["weight"], psf=cut["psf"], psf_oversampling=cut["k"],
                                   jacobian=cut["J"], offset=tuple(cut["offset"]), flux_scale=cut["ccd"].flux_scale,
                                   psf_moffat=cut["moffat"]))
        except ShearfitValueError as exc:
            log.warning("exposure %d CCD %s skipped for an object: %s", cut["e"], cut["ccd"].label, exc)
            continue
        psf_stats.append(psf_ellipticity(cut["psf"], cut["J"], cut["k"], moments=cut["moments"])
                         + (psf_fwhm_arcsec(cut["J"], cut["k"], moments=cut["moments"]),))
    if len(obs) < max(pc.min_exposures, 1):
        return {"fitclass": FITCLASS_FEW_EXPOSURES, "n_exposures_used": len(obs)}
    if cfg.calibration == "metacal":
        from ..calib.metacal import SHEARED, measure_metacal   # GalSim is imported only for metacal runs

        rng = np.random.default_rng([int(pc.metacal_seed) & _U64, int(obj_id) & _U64])
        if pc.metacal_noise_sign < 0:   # the antithetic twin of a simulated field: minus the same noise
            from ..simulate.stamps import NegatedNormal

            rng = NegatedNormal(rng)
        mc = measure_metacal(obs, mag, cfg.fit, pc.metacal_delta, rng, psf=pc.metacal_psf, replay=pc.metacal_replay,
                             own_samples=pc.metacal_own_grid, own_position=pc.metacal_own_position)
        res = mc.noshear
        extra = {f"{q}_{v}": getattr(mc.results[v], q) for v in SHEARED for q, _, _ in METACAL_QUANTITIES}
        extra.update({f"R{i + 1}{j + 1}": float(mc.R[i, j]) for i in range(2) for j in range(2)})
    else:
        seed = [int(pc.metacal_seed) & _U64, int(obj_id) & _U64, 1] if cfg.fit.noise_bias_correction else None
        res = measure_object(obs, mag, cfg.fit, noise_seed=seed)
        extra = {}
    row = {"e1": res.e1, "e2": res.e2, "weight": res.weight, "e_var": res.e_var, "fitclass": res.fitclass,
           "snr": res.snr, "scalelength": res.scalelength, "bulge_fraction": res.bulge_fraction,
           "model_flux": res.model_flux, "n_exposures_used": res.n_exposures_used, "star_pvalue": res.star_pvalue,
           "flux_snr": res.flux_snr, "round_scalelength": res.round_scalelength}
    row.update(extra)
    pe = np.array(psf_stats, float)
    with warnings.catch_warnings():   # an object whose PSF moments failed everywhere: NaN, silently
        warnings.simplefilter("ignore", RuntimeWarning)
        row["psf_e1"], row["psf_e2"], row["psf_fwhm"] = np.nanmean(pe, axis=0)
    if res.fitclass == FITCLASS_FIT_FAILED:
        log.debug("fit failed: %s", res.message)
    return row
