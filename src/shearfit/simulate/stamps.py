"""GalSim postage-stamp simulations of lensfit's galaxy population.

GalSim is the independent reference renderer here: nothing in this module
uses shearfit's own model code, so a ring test built on it checks the engine
against images it did not make.

Conventions (docs/interface.rst, "Python API for one object")
-------------------------------------------------------------
* Arrays are ``image[y, x]``; the stamp centre is index ``(ny // 2, nx // 2)``.
  ``offset=(dx, dy)`` puts the profile centre at ``x = nx // 2 + dx``,
  ``y = ny // 2 + dy``.
* Profiles and PSFs live in the world frame (u, v), arcsec. A pixel maps to it
  through ``J = [[du/dx, du/dy], [dv/dx, dv/dy]]``, i.e.
  ``galsim.JacobianWCS(J[0, 0], J[0, 1], J[1, 0], J[1, 1])``.
* Ellipticity is the paper's ``e = (a - b) / (a + b) exp(2 i theta)``, which is
  GalSim's reduced shear ``g``; intrinsic shapes keep the semi-major axis
  fixed (paper App. A) and the lensing shear composes as eq. (1).
"""

from __future__ import annotations

import copy
import math
from typing import Mapping

import galsim
import numpy as np

from ..errors import ShearfitValueError
from ..observation import Observation

__all__ = [
    "galaxy_profile",
    "intrinsic_shape",
    "moffat_psf",
    "kolmogorov_psf",
    "jacobian_wcs",
    "draw_stamp",
    "draw_psf_image",
    "make_observations",
    "noise_for_snr",
    "mag_to_flux",
    "ring_set",
    "ZERO_POINT",
]

#: AB zero point of simulated counts, as for ``model_flux`` in the catalogue.
ZERO_POINT = 30.0


# ----------------------------------------------------------------------------
# profiles
# ----------------------------------------------------------------------------

def intrinsic_shape(prof: galsim.GSObject, e1: float, e2: float) -> galsim.GSObject:
    """Give ``prof`` the ellipticity (e1, e2) keeping its semi-major axis fixed.

    A reduced shear of modulus |e| along its axis stretches that axis by
    ``sqrt((1 + |e|) / (1 - |e|)) = 1 / sqrt(q)``; a flux-conserving dilation by
    ``sqrt(q)`` first cancels that stretch, so the major axis keeps the round
    profile's length and the minor axis becomes ``q`` times it (paper App. A).
    """
    emod = math.hypot(e1, e2)
    if not emod < 1.0:
        raise ShearfitValueError(f"intrinsic ellipticity |e| = {emod:.6g} must be below 1")
    if emod == 0.0:
        return prof
    q = (1.0 - emod) / (1.0 + emod)
    return prof.dilate(math.sqrt(q)).shear(g1=e1, g2=e2)


#: Half-light radius of an exponential profile in units of its scalelength.
_EXP_HLR = 1.6783469900166608


def galaxy_profile(scalelength, bulge_fraction, e1, e2, flux=1.0, g1=0.0, g2=0.0, is_bulge=False,
                   truncation=4.5, gsparams=None, bulge_size_ratio=1.0, sersic_n=None) -> galsim.GSObject:
    """The paper's bulge + disk galaxy as a GalSim profile in world (arcsec) units.

    Parameters
    ----------
    scalelength : float
        Semi-major-axis exponential scalelength ``r`` of the disk, arcsec; the
        bulge's half-light radius is ``bulge_size_ratio * r`` (sec. 3.1).
    bulge_fraction : float
        B/T, the bulge's share of the total flux, in [0, 1].
    e1, e2 : float
        Intrinsic ellipticity (a - b)/(a + b), shared by bulge and disk.
    flux : float
        Total flux of the final profile.
    g1, g2 : float
        Reduced lensing shear applied after the intrinsic shape (eq. 1).
    is_bulge : bool
        True for a bulge-dominated galaxy: a pure de Vaucouleurs profile, and
        ``bulge_fraction`` is ignored.
    truncation : float
        Truncation radius along the major axis in units of ``r`` (disk
        scalelengths, bulge half-light radii), 4.5 in the paper.
    gsparams : galsim.GSParams, optional
        Accuracy settings passed to the components.
    bulge_size_ratio : float
        Bulge half-light radius over disk scalelength (1 in the paper).
    sersic_n : float, optional
        A galaxy outside the paper's models: one Sersic profile of this index
        with the half-light radius of an exponential disk of scalelength
        ``scalelength``, truncated at ``truncation * scalelength``
        (``bulge_fraction`` and ``is_bulge`` are ignored).

    Returns
    -------
    galsim.GSObject
        The sheared profile, of total flux ``flux``.
    """
    r = float(scalelength)
    if not r > 0:
        raise ShearfitValueError(f"scalelength must be positive, got {scalelength!r}")
    if sersic_n is not None and np.isfinite(sersic_n) and sersic_n > 0:
        prof = galsim.Sersic(n=float(sersic_n), half_light_radius=_EXP_HLR * r, trunc=truncation * r,
                             flux_untruncated=True, gsparams=gsparams)
        prof = intrinsic_shape(prof, float(e1), float(e2))
        if g1 != 0.0 or g2 != 0.0:
            prof = prof.shear(g1=float(g1), g2=float(g2))
        return prof.withFlux(float(flux))
    B = 1.0 if is_bulge else float(bulge_fraction)
    if not 0.0 <= B <= 1.0:
        raise ShearfitValueError(f"bulge_fraction must lie in [0, 1], got {bulge_fraction!r}")
    components = []
    if B < 1.0:
        # scale_radius fixes the profile exp(-R/r) itself, so the cut changes only the flux.
        disk = galsim.Sersic(n=1, scale_radius=r, trunc=truncation * r, gsparams=gsparams)
        components.append(disk.withFlux(1.0 - B))
    if B > 0.0:
        rb = bulge_size_ratio * r
        # The paper's r_h belongs to the untruncated exp(-7.67 (R/r_h)^(1/4)); GalSim would
        # otherwise rescale the profile so that the *truncated* one has that half-light radius.
        bulge = galsim.DeVaucouleurs(half_light_radius=rb, trunc=truncation * rb, flux_untruncated=True,
                                     gsparams=gsparams)
        components.append(bulge.withFlux(B))
    prof = components[0] if len(components) == 1 else galsim.Add(components, gsparams=gsparams)
    prof = intrinsic_shape(prof, float(e1), float(e2))
    if g1 != 0.0 or g2 != 0.0:
        prof = prof.shear(g1=float(g1), g2=float(g2))
    return prof.withFlux(float(flux))


def moffat_psf(fwhm, beta, e1=0.0, e2=0.0, gsparams=None) -> galsim.GSObject:
    """An elliptical Moffat PSF in world units (arcsec), unit flux.

    Parameters
    ----------
    fwhm : float
        FWHM of the circular Moffat before the (area-preserving) shear, arcsec.
    beta : float
        Moffat index.
    e1, e2 : float
        Ellipticity as reduced shear, (a - b)/(a + b).
    """
    return _sheared(galsim.Moffat(beta=float(beta), fwhm=float(fwhm), gsparams=gsparams), e1, e2)


def kolmogorov_psf(fwhm, e1=0.0, e2=0.0, gsparams=None) -> galsim.GSObject:
    """An elliptical Kolmogorov PSF (long-exposure atmospheric seeing) in world units (arcsec), unit flux: a
    PSF outside the Moffat family, with wings falling as r^(-11/3).

    Parameters as :func:`moffat_psf`, less the Moffat index.
    """
    return _sheared(galsim.Kolmogorov(fwhm=float(fwhm), gsparams=gsparams), e1, e2)


def _sheared(psf, e1, e2):
    """``psf`` given the ellipticity (e1, e2) as reduced shear (area-preserving); unchanged where it is 0."""
    return psf.shear(g1=float(e1), g2=float(e2)) if e1 != 0.0 or e2 != 0.0 else psf


def jacobian_wcs(jacobian) -> galsim.JacobianWCS:
    """``galsim.JacobianWCS`` of ``J = [[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec / pixel)."""
    J = np.asarray(jacobian, dtype=np.float64)
    if J.shape != (2, 2) or not np.all(np.isfinite(J)) or np.linalg.det(J) == 0:
        raise ShearfitValueError("jacobian must be a finite, invertible 2x2 array")
    return galsim.JacobianWCS(J[0, 0], J[0, 1], J[1, 0], J[1, 1])


# ----------------------------------------------------------------------------
# drawing
# ----------------------------------------------------------------------------

def draw_stamp(profile, psf, jacobian, offset=(0.0, 0.0), stamp_size=48, gsparams=None, psf_cache=None) -> np.ndarray:
    """Noise-free stamp of ``profile`` convolved with ``psf`` and the pixel, in counts.

    Parameters
    ----------
    profile, psf : galsim.GSObject
        In world (arcsec) units.
    jacobian : 2x2 array
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]``.
    offset : (dx, dy)
        Profile centre minus the stamp centre ``(nx // 2, ny // 2)``, pixels.
    stamp_size : int or (ny, nx)
        Stamp shape.
    gsparams : galsim.GSParams, optional
        Accuracy settings for the convolution.
    psf_cache : dict, optional
        Keeps the PSF's (and pixel's) transform on the k-space grid of GalSim's FFT drawing, keyed by the
        PSF, the Jacobian and the grid, so that other galaxies drawn with the same PSF and Jacobian onto the
        same grid (the members of a ring, the +g and -g runs) multiply it instead of evaluating the PSF
        again. The stamp is GalSim's ``drawImage`` (``method="auto"``) to rounding: the same grid, the same
        transforms, only the product's order differs.

    Returns
    -------
    ndarray of shape (ny, nx), float64
    """
    ny, nx = _shape2(stamp_size)
    conv = galsim.Convolve([profile, psf], gsparams=gsparams)
    if psf_cache is not None:
        return _draw_stamp_psf_cached(conv, jacobian, offset, nx, ny, psf_cache)
    # use_true_center=False centres on GalSim's image.center, which is 0-based index
    # (nx // 2, ny // 2) for odd and even sizes alike: the convention of docs/interface.rst.
    img = conv.drawImage(nx=nx, ny=ny, wcs=jacobian_wcs(jacobian), method="auto", use_true_center=False,
                         offset=(float(offset[0]), float(offset[1])), dtype=np.float64)
    return np.array(img.array, dtype=np.float64)


def _draw_stamp_psf_cached(conv, jacobian, offset, nx, ny, cache):
    """:func:`draw_stamp` by GalSim's FFT drawing in parts (``drawFFT_makeKImage`` / ``drawFFT_finish``):
    what ``conv.drawImage(nx=nx, ny=ny, wcs=..., method="auto", use_true_center=False, offset=offset)``
    draws, with the transform of the PSF and pixel taken from ``cache``."""
    wcs = jacobian_wcs(jacobian)
    gsp = conv.gsparams
    profile, psf = conv.obj_list       # with the convolution's gsparams, as drawImage evaluates them
    off = galsim.PositionD(float(offset[0]), float(offset[1]))
    pixel = galsim.Pixel(scale=1.0, gsparams=gsp)
    # the profile drawImage draws: in image coordinates, shifted by the offset, convolved with the pixel
    full = galsim.Convolve(wcs.profileToImage(conv, offset=off), pixel, gsparams=gsp)
    if full.is_analytic_x:    # pragma: no cover - a convolution with the pixel is not
        raise ShearfitValueError("draw_stamp: psf_cache needs FFT drawing")
    image = galsim.ImageD(nx, ny, scale=1.0)
    image.setCenter(0, 0)
    kimage, wrap = full.drawFFT_makeKImage(image)
    b = kimage.bounds
    key = (psf, np.asarray(jacobian, np.float64).tobytes(), b.xmin, b.xmax, b.ymin, b.ymax, kimage.scale)
    psf_k = cache.get(key)
    if psf_k is None:
        kp = galsim.ImageCD(bounds=b, scale=kimage.scale)
        galsim.Convolve(wcs.profileToImage(psf), pixel, gsparams=gsp)._drawKImage(kp)
        psf_k = cache[key] = kp.array.copy()
        psf_k.setflags(write=False)
    wcs.profileToImage(profile, offset=off)._drawKImage(kimage)
    kimage.array[...] *= psf_k
    full.drawFFT_finish(image, kimage, wrap, False)
    return np.array(image.array, dtype=np.float64)


def draw_psf_image(psf, jacobian, size=None, oversampling=1, gsparams=None) -> np.ndarray:
    """PSF image for an :class:`~shearfit.Observation`: pixel response included, unit sum.

    The PSF is centred on index ``(n // 2, n // 2)``. With ``oversampling=k`` the
    array samples the pixel-convolved PSF every ``1/k`` pixel, so its
    ``[::k, ::k]`` subsampling is (up to normalisation) the native image.

    Parameters
    ----------
    psf : galsim.GSObject
        PSF in world units.
    jacobian : 2x2 array
        Pixel-to-world Jacobian of the exposure.
    size : int, optional
        Array side; default ``48 * oversampling`` (even: the engine pads or crops).
    oversampling : int
        PSF samples per image pixel.

    Returns
    -------
    ndarray of shape (size, size), summing to one
    """
    k = int(oversampling)
    if k < 1 or k != oversampling:
        raise ShearfitValueError(f"oversampling must be a positive integer, got {oversampling!r}")
    n = 48 * k if size is None else int(size)
    wcs = jacobian_wcs(jacobian)
    if k == 1:
        img = psf.drawImage(nx=n, ny=n, wcs=wcs, method="auto", use_true_center=False, dtype=np.float64)
    else:
        # The pixel response belongs to the native pixel, so build it in the native frame and
        # sample the convolution on a grid k times finer with no further pixel integration.
        pixel = wcs.toWorld(galsim.Pixel(1.0))
        fine = jacobian_wcs(np.asarray(jacobian, dtype=np.float64) / k)
        img = galsim.Convolve([psf, pixel], gsparams=gsparams).drawImage(
            nx=n, ny=n, wcs=fine, method="no_pixel", use_true_center=False, dtype=np.float64)
    arr = np.array(img.array, dtype=np.float64)
    # Flux in wings beyond the array (a few 1e-3 for beta ~ 2.5) is dropped: the engine
    # requires a unit sum, and that is what a PSF estimated from stars would give too.
    return arr / arr.sum()


def noise_for_snr(noise_free_stamps, snr) -> float:
    """One Gaussian pixel sigma, the same on every exposure, giving the requested SNR.

    The combined profile-weighted SNR is ``sqrt(sum_exposures sum_pixels m^2) / sigma``
    for noise-free stamps ``m`` (counts).

    Parameters
    ----------
    noise_free_stamps : array or sequence of arrays
    snr : float

    Returns
    -------
    float
    """
    if not snr > 0:
        raise ShearfitValueError(f"snr must be positive, got {snr!r}")
    if isinstance(noise_free_stamps, np.ndarray):
        noise_free_stamps = [noise_free_stamps]
    power = sum(float(np.sum(np.square(np.asarray(m, dtype=np.float64)))) for m in noise_free_stamps)
    if not power > 0:
        raise ShearfitValueError("noise-free stamps carry no signal")
    return math.sqrt(power) / float(snr)


def make_observations(profile, psfs, jacobians, offsets, noise_sigmas, rng, stamp_size=48, psf_oversampling=1,
                      flux_scales=None, gsparams=None, noise_free=None, psf_images=None, add_noise=True) -> list:
    """Simulate one object on several exposures and wrap each as an :class:`~shearfit.Observation`.

    Parameters
    ----------
    profile : galsim.GSObject or None
        The galaxy in world units, flux in units of the common flux (may be
        None when ``noise_free`` is given).
    psfs : sequence of galsim.GSObject
        One PSF per exposure.
    jacobians : 2x2 array or sequence of them
        Per exposure (a single one is used for all).
    offsets : sequence of (dx, dy)
        Per exposure; the object is drawn there and the Observation's nominal
        offset is the same.
    noise_sigmas : float or sequence of float
        Gaussian pixel noise sigma per exposure, counts; the weight is
        ``1 / sigma**2``. A sigma of 0 gives a noise-free stamp with unit
        weight (an arbitrary scale: only relative weights matter there).
    rng : numpy.random.Generator
        Source of the noise.
    stamp_size : int
    psf_oversampling : int
    flux_scales : sequence of float, optional
        Counts per unit of the common flux on each exposure (default 1).
    gsparams : galsim.GSParams, optional
    noise_free : list of arrays, optional
        Already-drawn noise-free stamps (``flux_scales`` applied) to reuse.
    psf_images : list of arrays, optional
        Already-drawn PSF images (as :func:`draw_psf_image` makes them) to reuse.

    Returns
    -------
    list of Observation
    """
    n = len(psfs)
    Js = _per_exposure_jacobians(jacobians, n)
    offs = np.asarray(offsets, dtype=np.float64).reshape(n, 2)
    sig = np.broadcast_to(np.asarray(noise_sigmas, dtype=np.float64), (n,))
    fs = np.ones(n) if flux_scales is None else np.broadcast_to(np.asarray(flux_scales, dtype=np.float64), (n,))
    if noise_free is None:
        noise_free = [draw_stamp(profile * fs[i], psfs[i], Js[i], offs[i], stamp_size, gsparams) for i in range(n)]
    obs = []
    for i in range(n):
        m = noise_free[i]
        if sig[i] > 0:
            # add_noise=False keeps the noise-free image but the weights of sigma: the likelihood then
            # has the width of that SNR and is centred on the truth (the expected likelihood of App. C)
            image = m + rng.normal(0.0, sig[i], size=m.shape) if add_noise else m.copy()
            ivar = 1.0 / sig[i] ** 2
        else:
            image = m.copy()
            ivar = 1.0
        psf_img = (psf_images[i] if psf_images is not None
                   else draw_psf_image(psfs[i], Js[i], oversampling=psf_oversampling, gsparams=gsparams))
        obs.append(Observation(image=image, weight=np.full(m.shape, ivar), psf=psf_img,
                               psf_oversampling=psf_oversampling, jacobian=Js[i], offset=tuple(offs[i]),
                               flux_scale=float(fs[i])))
    return obs


def mag_to_flux(mag, zero_point=ZERO_POINT):
    """Counts of an AB magnitude for the given zero point."""
    return 10.0 ** (-0.4 * (np.asarray(mag, dtype=np.float64) - zero_point))


# ----------------------------------------------------------------------------
# ring tests
# ----------------------------------------------------------------------------

class NegatedNormal:
    """A numpy Generator whose ``normal`` draws come out negated (the same state consumed): the noise of
    an antithetic twin, which leaves every other draw, and so the galaxies, unchanged."""

    def __init__(self, rng):
        self.rng = rng

    def normal(self, *args, **kwargs):
        return -self.rng.normal(*args, **kwargs)

    def __getattr__(self, name):
        if name == "rng":   # not set yet (a copy or an unpickling in progress): no recursion through this method
            raise AttributeError(name)
        return getattr(self.rng, name)


class _RecordedNormal:
    """A numpy Generator whose ``normal`` draws are kept (``drawn``), every other draw passed through."""

    def __init__(self, rng):
        self.rng = rng
        self.drawn = []

    def normal(self, *args, **kwargs):
        z = self.rng.normal(*args, **kwargs)
        self.drawn.append(z)
        return z

    def __getattr__(self, name):
        if name == "rng":   # not set yet (a copy or an unpickling in progress): no recursion through this method
            raise AttributeError(name)
        return getattr(self.rng, name)


class _ReplayedNormal:
    """``normal`` returns another generator's recorded draws negated, in their order: the twin's noise without
    drawing it again (the numbers :class:`NegatedNormal` of a generator in the same state gives)."""

    def __init__(self, drawn):
        self.drawn = iter(drawn)

    def normal(self, *args, **kwargs):
        return -next(self.drawn)


def ring_set(n_galaxies, shear, rng, n_rotations=4, n_exposures=7, snr_range=(100, 200), mag_range=(21, 24.5),
             psf_fwhm_range=(0.5, 0.8), psf_beta_range=(2.5, 4.5), psf_e_max=0.1, pixel_scale=0.187,
             stamp_size=48, psf_oversampling=1, max_dither=0.5, cfg=None, noise_seed=None,
             rotate_exposures=False, gsparams=None, population=None, add_noise=True, noise_sign=1,
             jacobian_jitter=0.0, profile=None, noise_sigma=None, psf_e_fixed=None, antithetic=False,
             draw_cache=None, psf_family="moffat"):
    """Ring sets of GalSim-simulated galaxies, all with one applied shear.

    Every galaxy is drawn from the paper's population at a magnitude uniform in
    ``mag_range`` and appears at ``n_rotations`` orientations (intrinsic e
    rotated by ``2 pi j / n_rotations`` in the e-plane). Per galaxy, each
    exposure has its own elliptical Moffat PSF, a sub-pixel dither and
    (optionally) a rotated pixel grid; these are shared by the orientations,
    which differ only in shape and noise. One pixel sigma per galaxy, common to
    all its exposures and orientations, gives the galaxy's target SNR on the
    *unsheared* rotation-0 stamps, so that ``+g`` and ``-g`` runs see identical
    noise.

    Parameters
    ----------
    n_galaxies : int
    shear : (g1, g2)
    rng : numpy.random.Generator
        Drives every random choice (and the noise unless ``noise_seed`` is
        given). Two calls with generators in the same state and opposite
        shears produce the same galaxies, PSFs, dithers and noise: nothing
        drawn depends on the shear.
    n_rotations : int
    n_exposures : int
    snr_range : (float, float)
        Target SNR, uniform.
    mag_range : (float, float)
        Magnitude, uniform; sets the size prior and the flux (zero point 30).
    psf_fwhm_range, psf_beta_range : (float, float)
        Moffat FWHM (arcsec) and beta, uniform per exposure.
    psf_e_max : float
        PSF |e| is uniform in [0, psf_e_max], at a uniform random angle.
    psf_family : {"moffat", "kolmogorov"}
        The exposures' PSF profile: the elliptical Moffat, or an elliptical Kolmogorov of the same FWHM and
        ellipticity (:func:`kolmogorov_psf`; the Moffat index is drawn all the same and not used, so that every
        other draw is the same).
    psf_e_fixed : (float, float), optional
        Every exposure's PSF ellipticity (e1, e2) instead (the random ones are still drawn, so every
        other draw is the same): with one PSF direction for all galaxies, the additive bias c of a ring
        test is the PSF leakage alpha e_psf, which random directions average away.
    pixel_scale : float
        Arcsec per pixel.
    stamp_size : int
    psf_oversampling : int
    max_dither : float
        Dither offsets uniform in [-max_dither, max_dither] pixels per axis.
    cfg : FitConfig, optional
        Population settings for :func:`shearfit.engine.priors.sample_population` and
        the truncation radius.
    noise_seed : int or sequence of int, optional
        When given, the noise of galaxy ``i``, orientation ``j`` comes from
        ``numpy.random.default_rng([*noise_seed, i, j])`` instead of ``rng``,
        so it is fixed whatever else the caller changes.
    rotate_exposures : bool
        Give each exposure's pixel grid a random rotation angle (Jacobian
        ``pixel_scale * R(phi)``).
    gsparams : galsim.GSParams, optional
    population : callable, optional
        ``population(mags, rng, cfg)`` replacing the default population sampler; a ``mag``
        field in what it returns replaces the drawn magnitude (and with it the flux).
    profile : callable, optional
        ``profile(fields, angle, g1, g2, flux, gsparams)``: the galaxy's GalSim profile from its
        population fields (a dict of scalars), turned by ``angle`` radians as a whole and sheared,
        instead of :func:`galaxy_profile` of the fields (e.g.
        :func:`shearfit.simulate.outside.outside_profile`: galaxies outside the model family). Ring
        member j is then the galaxy turned by ``pi j / n_rotations``, and its ``e1_int``, ``e2_int``
        are those of the population fields turned the same way.
    noise_sign : +1 or -1
        -1 negates every noise draw (the antithetic twin of the same
        galaxies, PSFs and dithers: its noise is exactly minus the +1 run's).
    antithetic : bool
        Also return each orientation's antithetic twin, right after it: the same noise-free stamps and PSF
        images with minus its noise, the numbers a second call with the opposite ``noise_sign`` and a
        generator in the same state gives, without drawing the stamps again.
    draw_cache : dict, optional
        Shared by calls that draw the same galaxies (generators in the same state, other shears: a ring
        test's +g and -g runs): what does not depend on the shear, the PSF images, the PSFs' transforms
        on GalSim's FFT grids (:func:`draw_stamp`'s ``psf_cache``) and the unsheared stamps that set the
        noise, is drawn once. The stamps are the same to rounding. Without it, each galaxy keeps them for
        its own orientations.
    noise_sigma : float, optional
        One pixel sigma (counts) for every galaxy instead of the target SNR's:
        the SNR then follows from the magnitude's flux and the galaxy's size, as
        on a survey field of that depth, and ``snr_range`` is not used.
    jacobian_jitter : float
        Multiply each exposure's Jacobian by ``1 + A``, A a 2x2 matrix of
        normal deviates of this rms (a camera's distortion at the dithered
        positions of one object: about 1e-4 to 1e-3); 0 leaves them equal.

    Returns
    -------
    list of (list of Observation, dict)
        ``n_galaxies * n_rotations`` entries, galaxy-major. The truth dict has
        ``galaxy``, ``rotation``, ``e1_int``, ``e2_int`` (this orientation's),
        ``g1``, ``g2``, ``scalelength``, ``bulge_fraction``, ``is_bulge``,
        ``mag``, ``flux``, ``snr`` (target; with ``noise_sigma``, that of the unsheared
        galaxy), ``snr_true`` (of this orientation's
        noise-free stamps), ``sigma``, ``psf_fwhm``, ``psf_beta``, ``psf_e1``,
        ``psf_e2``, ``offsets``, ``jacobian_angles``, ``jacobians``, ``n_redraws`` and ``noise_sign``. With
        ``antithetic``, twice as many: each orientation followed by its twin.
    """
    g1, g2 = (float(s) for s in shear)
    if math.hypot(g1, g2) >= 1:
        raise ShearfitValueError("shear must have |g| < 1")
    n_rotations = int(n_rotations)
    if n_rotations < 1 or n_galaxies < 0 or n_exposures < 1:
        raise ShearfitValueError("n_rotations and n_exposures must be positive, n_galaxies non-negative")
    sampler = population if population is not None else _population_sampler()
    truncation = float(getattr(cfg, "truncation", 4.5))
    bulge_ratio = float(getattr(cfg, "bulge_size_ratio", 1.0))
    seed_prefix = None if noise_seed is None else list(np.atleast_1d(noise_seed).astype(np.int64))
    if psf_family not in ("moffat", "kolmogorov"):
        raise ShearfitValueError(f"psf_family: {psf_family!r} is not 'moffat' or 'kolmogorov'")

    out = []
    for i in range(int(n_galaxies)):
        gal = _draw_galaxy(rng, sampler, cfg, n_exposures, snr_range, mag_range, psf_fwhm_range, psf_beta_range,
                           psf_e_max, pixel_scale, stamp_size, max_dither, truncation, rotate_exposures)
        if psf_e_fixed is not None:
            gal["psf_e1"] = np.full(n_exposures, float(psf_e_fixed[0]))
            gal["psf_e2"] = np.full(n_exposures, float(psf_e_fixed[1]))
        psfs = [moffat_psf(f, b, pe1, pe2, gsparams=gsparams) if psf_family == "moffat" else
                kolmogorov_psf(f, pe1, pe2, gsparams=gsparams)
                for f, b, pe1, pe2 in zip(gal["psf_fwhm"], gal["psf_beta"], gal["psf_e1"], gal["psf_e2"])]
        Js = [pixel_scale * _rotation(a) for a in gal["jacobian_angles"]]
        if jacobian_jitter > 0:
            Js = [J @ (np.eye(2) + rng.normal(0.0, jacobian_jitter, (2, 2))) for J in Js]
        cache = {} if draw_cache is None else draw_cache
        psf_images = [_cached(cache, ("psf_image", p, J.tobytes(), psf_oversampling, gsparams),
                              lambda p=p, J=J: draw_psf_image(p, J, oversampling=psf_oversampling, gsparams=gsparams))
                      for p, J in zip(psfs, Js)]

        def stamps(e1, e2, sg1, sg2, turn=0.0):
            if profile is not None:
                # the whole galaxy turned by `turn` (pi j / n_rotations for ring member j)
                prof = profile(gal["fields"], turn, sg1, sg2, gal["flux"], gsparams)
            else:
                prof = galaxy_profile(gal["scalelength"], gal["bulge_fraction"], e1, e2, flux=gal["flux"], g1=sg1,
                                      g2=sg2, is_bulge=gal["is_bulge"], truncation=truncation, gsparams=gsparams,
                                      bulge_size_ratio=bulge_ratio, sersic_n=gal["sersic_n"])
            key = ("stamps", prof, tuple(psfs), np.array(Js).tobytes(), gal["offsets"].tobytes(), str(stamp_size),
                   gsparams) if sg1 == 0.0 and sg2 == 0.0 else None
            return _cached(cache, key, lambda: [draw_stamp(prof, p, J, o, stamp_size, gsparams, psf_cache=cache)
                                                for p, J, o in zip(psfs, Js, gal["offsets"])])

        # The sigma must not depend on the sign of the shear, else the noise would not cancel
        # between +g and -g runs: take it from the unsheared galaxy.
        if noise_sigma is None:
            sigma = noise_for_snr(stamps(gal["e1"], gal["e2"], 0.0, 0.0), gal["snr"])
        else:
            sigma = float(noise_sigma)
            gal["snr"] = noise_for_snr(stamps(gal["e1"], gal["e2"], 0.0, 0.0), sigma)
        e_int = complex(gal["e1"], gal["e2"])
        for j in range(n_rotations):
            ej = e_int * np.exp(2j * np.pi * j / n_rotations)
            m = stamps(ej.real, ej.imag, g1, g2, np.pi * j / n_rotations)
            noise_rng = rng if seed_prefix is None else np.random.default_rng(seed_prefix + [i, j])
            if noise_sign < 0:
                noise_rng = NegatedNormal(noise_rng)
            if antithetic:
                noise_rng = _RecordedNormal(noise_rng)
            obs = make_observations(None, psfs, Js, gal["offsets"], sigma, noise_rng, stamp_size=stamp_size,
                                    psf_oversampling=psf_oversampling, gsparams=gsparams, noise_free=m,
                                    psf_images=psf_images, add_noise=add_noise)
            members = [(obs, 1 if noise_sign >= 0 else -1)]
            if antithetic:
                twin = make_observations(None, psfs, Js, gal["offsets"], sigma, _ReplayedNormal(noise_rng.drawn),
                                         stamp_size=stamp_size, psf_oversampling=psf_oversampling, gsparams=gsparams,
                                         noise_free=m, psf_images=psf_images, add_noise=add_noise)
                members.append((twin, -members[0][1]))
            truth = {
                "galaxy": i, "rotation": j, "e1_int": float(ej.real), "e2_int": float(ej.imag), "g1": g1, "g2": g2,
                "scalelength": gal["scalelength"], "bulge_fraction": gal["bulge_fraction"],
                "is_bulge": gal["is_bulge"], "mag": gal["mag"], "flux": gal["flux"], "snr": gal["snr"],
                "snr_true": noise_for_snr(m, 1.0) / sigma, "sigma": sigma,
                "psf_fwhm": gal["psf_fwhm"].copy(), "psf_beta": gal["psf_beta"].copy(),
                "psf_e1": gal["psf_e1"].copy(), "psf_e2": gal["psf_e2"].copy(), "offsets": gal["offsets"].copy(),
                "jacobian_angles": gal["jacobian_angles"].copy(), "n_redraws": gal["n_redraws"],
                "jacobians": np.array(Js), "fields": dict(gal["fields"]),
            }
            for k, (o, sign) in enumerate(members):
                out.append((o, dict(truth if k == 0 else copy.deepcopy(truth), noise_sign=sign)))
    return out


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------

def _cached(cache, key, make):
    """``make()``, kept in ``cache`` under ``key`` (None: not kept); a copy of what is kept is returned, so
    that a caller changing it does not change the cache."""
    if key is None:
        return make()
    try:
        value = cache[key]
    except KeyError:
        value = cache[key] = make()
    except TypeError:   # an unhashable profile: drawn each time
        return make()
    return copy.deepcopy(value)


def _draw_galaxy(rng, sampler, cfg, n_exposures, snr_range, mag_range, psf_fwhm_range, psf_beta_range, psf_e_max,
                 pixel_scale, stamp_size, max_dither, truncation, rotate_exposures, max_tries=1000):
    """Galaxy and exposure parameters, redrawn until the galaxy fits its stamp.

    Every draw is independent of the shear, which is what lets +g and -g runs
    with equal generator states share galaxies and noise.
    """
    half = 0.5 * min(_shape2(stamp_size)) * pixel_scale
    for tries in range(max_tries):
        mag = float(rng.uniform(*mag_range))
        pop = sampler(np.array([mag]), rng, cfg)
        # a population may choose the magnitude itself (the galaxies of a simulated field, say)
        mag = float(_field(pop, "mag")) if _has_field(pop, "mag") else mag
        r = float(_field(pop, "scalelength"))
        fwhm = rng.uniform(*psf_fwhm_range, size=n_exposures)
        beta = rng.uniform(*psf_beta_range, size=n_exposures)
        pe = psf_e_max * rng.uniform(0.0, 1.0, size=n_exposures)
        pphi = rng.uniform(0.0, np.pi, size=n_exposures)
        offsets = rng.uniform(-max_dither, max_dither, size=(n_exposures, 2))
        angles = rng.uniform(0.0, 2 * np.pi, size=n_exposures) if rotate_exposures else np.zeros(n_exposures)
        snr = float(rng.uniform(*snr_range))
        # A truncated profile wider than the stamp (with the PSF's spread) would be clipped, and
        # the paper flags such objects rather than fitting them: keep them out of the test set.
        if truncation * r + 2.0 * float(np.max(fwhm)) > half:
            continue
        return {
            "mag": mag, "flux": float(mag_to_flux(mag)), "scalelength": r,
            "bulge_fraction": float(_field(pop, "bulge_fraction")), "is_bulge": bool(_field(pop, "is_bulge")),
            "e1": float(_field(pop, "e1")), "e2": float(_field(pop, "e2")),
            "sersic_n": float(_field(pop, "sersic_n")) if _has_field(pop, "sersic_n") else None,
            "psf_fwhm": fwhm, "psf_beta": beta, "psf_e1": pe * np.cos(2 * pphi), "psf_e2": pe * np.sin(2 * pphi),
            "offsets": offsets, "jacobian_angles": angles, "snr": snr, "n_redraws": tries,
            "fields": _fields(pop),
        }
    raise ShearfitValueError(f"no galaxy fitting a {stamp_size}-pixel stamp in {max_tries} draws; "
                             "enlarge the stamp or narrow the magnitude / PSF ranges")


def _population_sampler():
    # Imported late so that the simulation module loads even while priors.py is edited.
    from ..engine.priors import sample_population
    return sample_population


def _has_field(sample, name):
    if isinstance(sample, Mapping):
        return name in sample
    if isinstance(sample, np.ndarray) and sample.dtype.names:
        return name in sample.dtype.names
    return hasattr(sample, name)


def _fields(sample):
    """Every field of a one-galaxy population sample, as a dict of scalars."""
    if isinstance(sample, Mapping):
        names = list(sample)
    elif isinstance(sample, np.ndarray) and sample.dtype.names:
        names = list(sample.dtype.names)
    else:
        return {}
    return {k: _field(sample, k).item() for k in names}


def _field(sample, name):
    """Scalar ``name`` of a one-galaxy population sample (mapping, record array or object)."""
    if isinstance(sample, Mapping):
        v = sample[name]
    elif isinstance(sample, np.ndarray) and sample.dtype.names:
        v = sample[name]
    else:
        v = getattr(sample, name)
    return np.asarray(v).reshape(-1)[0]


def _rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _shape2(stamp_size):
    if np.ndim(stamp_size) == 0:
        n = int(stamp_size)
        return n, n
    ny, nx = (int(s) for s in stamp_size)
    return ny, nx


def _per_exposure_jacobians(jacobians, n):
    J = np.asarray(jacobians, dtype=np.float64)
    if J.shape == (2, 2):
        return [J] * n
    if J.shape != (n, 2, 2):
        raise ShearfitValueError(f"need one 2x2 jacobian or {n} of them, got shape {J.shape}")
    return list(J)
