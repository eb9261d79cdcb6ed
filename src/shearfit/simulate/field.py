"""Simulated survey fields: GalSim images in the input format of docs/interface.rst, plus ``truth.fits`` (sec. 8).

Two suites, as the paper's two independent simulation sets (sec. 8.1, 8.2):

``great``
    GREAT-like: galaxies of the paper's population (90 % disk-dominated
    with the bulge fraction of the prior, 10 % de Vaucouleurs, sizes from
    the magnitude-dependent prior, ellipticities from the disk and bulge
    priors, random orientations, optionally in 90-degree pairs) on a
    jittered grid, stars between them; several CCDs, ``n_exposures``
    exposures in a linear dither pattern, each with its own elliptical
    Moffat PSF (beta, FWHM, ellipticity drawn per exposure, with a small
    smooth variation over the field); sky noise, bad columns and cosmic
    rays (in the weight maps: weight 0).
``second``
    A different PSF family (Kolmogorov atmosphere convolved with a circular
    optical PSF: obscured pupil, defocus and spherical aberration), one
    exposure, random positions with overlaps allowed.

The shear is constant over a field (``shear: [g1, g2]``) or drawn from a
power spectrum (``shear_rms`` > 0: a Gaussian E-mode field from
``galsim.PowerSpectrum`` with P(k) proportional to k^-1.5, scaled to that
rms). Galaxy sizes are semi-major-axis disk scalelengths (the bulge's
half-light radius equals it); shapes keep the semi-major axis fixed and the
shear is applied as eq. (1) (``galaxy_profile``). The SNR of truth.fits is
the paper's: noise-free flux in a circular aperture of 5 pixels radius over
its noise, combined over exposures in quadrature.

Everything random comes from one seed, recorded in ``simulation.yaml`` and
in the header of ``truth.fits``: the same configuration and seed write the
same field.

``noise_sign: -1`` writes the same field with its pixel noise reversed
(header ``NOISESGN``; bad columns and cosmic rays are unchanged): the
antithetic twin of the ``noise_sign: 1`` field. The noise is Gaussian, so
n and -n are equally likely and each twin is an honest simulation; in the
mean of the two the terms of the estimate odd in the noise (the largest
part of its scatter) cancel, while the noise bias, even in the noise,
stays. Calibration sets use twins to measure the additive bias c, which
the +g / -g pairs (same noise) do not free of pixel noise.

``noise_sign: 0`` writes the field without its pixel noise, the weights (and
the defects) unchanged: measured, it gives the estimator's bias at the
field's weights without a noise realisation (the prior's pull at low SNR,
the model's own bias), against which the noisy field's shows what the noise
adds.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field, fields

import galsim
import numpy as np
import yaml
from astropy.io import fits
from astropy.table import Table, vstack

from ..files import atomic_path
from ..config import FitConfig
from ..errors import ShearfitValueError
from ..engine.priors import sample_population
from .stamps import galaxy_profile, mag_to_flux

__all__ = ["SimulationConfig", "PRESETS", "simulate_field", "simulation_config", "simulate_missing", "truth_galaxies"]

SNR_APERTURE = 5.0     # pixels (sec. 8.1)
ZERO_POINT = 30.0


@dataclass
class SimulationConfig:
    """Settings of a simulated field (YAML keys of ``shearfit simulate``)."""

    suite: str = "great"                 # great | second
    seed: int = 1
    n_exposures: int = 7
    n_ccd: int = 2
    ccd_nx: int = 512
    ccd_ny: int = 512
    pixel_scale: float = 0.187           # arcsec (MegaCam)
    ra: float = 35.0                     # field centre, degrees
    dec: float = -4.0
    dither: tuple = (7.3, -4.1)          # pixels per exposure, linear pattern
    exposure_rotation: float = 0.0       # degrees rms: each exposure's pixel grid turned on the sky by a normal
    #                                      deviate of this (a rotator's offsets), so that no two exposures share a
    #                                      Jacobian (0: every exposure aligned, their Fourier modes merge)
    grid_spacing: float = 40.0           # pixels between galaxies (great suite)
    galaxy_density: float = 30.0         # per arcmin^2 (second suite: random positions)
    mag_range: tuple = (20.0, 24.7)
    mag_slope: float = 0.3               # dN/dm proportional to 10^(slope m)
    max_scalelength: float = 1.5         # arcsec: larger draws are redrawn
    rotated_pairs: bool = True           # each galaxy also at 90 degrees (e -> -e), the next grid cell
    star_density: float = 0.0            # per arcmin^2; 0: one star per galaxy-grid cell corner (great suite)
    star_snr_range: tuple = (30.0, 300.0)   # per exposure (brighter stars would saturate)
    shear: tuple = (0.03, -0.02)
    shear_rms: float = 0.0               # > 0: a shear field from a power spectrum instead of a constant
    depth_mag: float = 24.5              # a point source this faint has SNR 10 (5-pixel aperture, all exposures)
    psf_fwhm_range: tuple = (0.55, 0.85)  # arcsec
    psf_beta_range: tuple = (2.5, 4.5)
    psf_e_max: float = 0.08
    psf_e_fixed: tuple = ()              # (e1, e2): every exposure's PSF this ellipticity (a coherent anisotropy)
    psf_variation: float = 0.02          # FWHM and e change by about this over the field
    bad_columns: int = 2                 # per CCD and exposure
    cosmic_rays: int = 10                # per CCD and exposure
    noise_sign: int = 1                  # -1: the same seed's pixel noise reversed (antithetic twin); 0: no noise
    give_psf: bool = True                # write the true PSF per exposure (``psf:`` in field.yaml)
    stamp_size: int = 48                 # the measurement's stamp
    fit_settings: dict = field(default_factory=dict)   # copied into field.yaml (psf_order, ...)

    def validate(self):
        if self.suite not in ("great", "second"):
            raise ShearfitValueError(f"simulation key suite: {self.suite!r} is not 'great' or 'second'")
        for name in ("n_exposures", "n_ccd", "ccd_nx", "ccd_ny"):
            if int(getattr(self, name)) < 1:
                raise ShearfitValueError(f"simulation key {name} must be positive")
        if float(np.hypot(*self.shear)) >= 0.5 or self.shear_rms < 0 or self.shear_rms > 0.2:
            raise ShearfitValueError("simulation keys shear / shear_rms: |g| must stay below 0.5, shear_rms in [0, 0.2]")
        if len(self.psf_e_fixed) not in (0, 2) or (len(self.psf_e_fixed) and np.hypot(*self.psf_e_fixed) >= 0.5):
            raise ShearfitValueError("simulation key psf_e_fixed: give [e1, e2] with |e| < 0.5, or leave it out")
        if self.mag_range[0] >= self.mag_range[1]:
            raise ShearfitValueError(f"simulation key mag_range: {list(self.mag_range)} is empty")
        if self.noise_sign not in (1, 0, -1):
            raise ShearfitValueError(f"simulation key noise_sign: {self.noise_sign!r} is not 1, 0 or -1")
        if not 0 <= float(self.exposure_rotation) <= 10:
            raise ShearfitValueError(f"simulation key exposure_rotation: {self.exposure_rotation!r} degrees must lie "
                                     "in [0, 10]")
        return self


PRESETS = {
    # seconds to run: the test suite's end-to-end checks (one small CCD, 3 exposures, a low-order PSF model)
    "tiny": dict(n_exposures=3, n_ccd=1, ccd_nx=320, ccd_ny=320, mag_range=(20.0, 23.0), bad_columns=1,
                 cosmic_rays=3, fit_settings={"psf_min_stars": 8, "psf_order": 1}),
    # a few hundred galaxies on 2 small CCDs: tests and the demo (stars dense enough for a PSF model per CCD)
    "small": dict(),
    # CFHTLenS-like: MegaCam-sized pixels, 4 CCDs of 2048 x 4096, 7 exposures, stars at a survey's density
    "cfhtlens": dict(n_ccd=4, ccd_nx=2048, ccd_ny=4096, star_density=1.5, grid_spacing=48.0),
    # the second suite: one exposure, Kolmogorov + optics, random positions
    "second-small": dict(suite="second", n_exposures=1, n_ccd=1, ccd_nx=768, ccd_ny=768, galaxy_density=60.0,
                         star_density=40.0, bad_columns=1, cosmic_rays=5),
    "second": dict(suite="second", n_exposures=1, n_ccd=4, ccd_nx=2048, ccd_ny=4096, galaxy_density=30.0,
                   star_density=1.5),
}


def simulation_config(mapping=None) -> SimulationConfig:
    """A configuration from a mapping: ``preset`` (default ``small``) and overrides."""
    mapping = dict(mapping or {})
    preset = mapping.pop("preset", "small")
    if preset not in PRESETS:
        raise ShearfitValueError(f"simulation key preset: {preset!r} is not one of {sorted(PRESETS)}")
    values = copy.deepcopy(PRESETS[preset])
    known = {f.name for f in fields(SimulationConfig)}
    for k, v in mapping.items():
        if k not in known:
            raise ShearfitValueError(f"unknown simulation key {k!r} (known: {', '.join(sorted(known))})")
        values[k] = v
    for k in ("dither", "mag_range", "star_snr_range", "shear", "psf_fwhm_range", "psf_beta_range", "psf_e_fixed"):
        if k in values:
            values[k] = tuple(float(x) for x in values[k])
    cfg = SimulationConfig(**values)
    cfg.preset = preset
    return cfg.validate()


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------

def _ccd_header(sc: SimulationConfig, ccd, exposure):
    """TAN header of one CCD in one exposure: CCDs side by side in x (20-pixel gaps), dithered."""
    dx, dy = sc.dither[0] * exposure, sc.dither[1] * exposure
    cd = sc.pixel_scale / 3600.0
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = sc.ra, sc.dec
    off = (ccd - 0.5 * (sc.n_ccd - 1)) * (sc.ccd_nx + 20)
    # north up, east left: x increases to the west
    h["CRPIX1"] = sc.ccd_nx / 2 + 0.5 - off + dx
    h["CRPIX2"] = sc.ccd_ny / 2 + 0.5 + dy
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = -cd, 0.0, 0.0, cd
    if sc.exposure_rotation > 0:
        # the exposure's turn (the same for its CCDs), about the tangent point: CD -> R(t) CD
        t = np.deg2rad(sc.exposure_rotation) * np.random.default_rng([sc.seed, 7919, exposure]).normal()
        c, s = np.cos(t), np.sin(t)
        h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = -c * cd, -s * cd, -s * cd, c * cd
    h["MAGZP"], h["GAIN"], h["SATURATE"] = ZERO_POINT, 1.0, 1e9
    h["CCDNUM"] = ccd + 1
    h["EXPNUM"] = exposure
    return h


def _field_extent(sc):
    """Half-widths (arcsec) of the area all CCDs cover, about the field centre."""
    wx = (sc.n_ccd * (sc.ccd_nx + 20) - 20) * sc.pixel_scale / 2
    wy = sc.ccd_ny * sc.pixel_scale / 2
    return wx, wy


def _to_radec(sc, du, dv):
    """Tangent-plane offsets (arcsec, +u west... here +u east as RA) to RA, Dec (gnomonic)."""
    centre = galsim.CelestialCoord(sc.ra * galsim.degrees, sc.dec * galsim.degrees)
    out = [centre.deproject(-u * galsim.arcsec, v * galsim.arcsec) for u, v in zip(du, dv)]
    return np.array([c.ra.deg for c in out]), np.array([c.dec.deg for c in out])


def _positions(sc, rng):
    """Galaxy and star positions (arcsec east, north of the centre)."""
    wx, wy = _field_extent(sc)
    margin = 30 * sc.pixel_scale
    if sc.suite == "great":
        s = sc.grid_spacing * sc.pixel_scale
        xs = np.arange(-wx + margin + s / 2, wx - margin, s)
        ys = np.arange(-wy + margin + s / 2, wy - margin, s)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        gal = np.stack([gx.ravel(), gy.ravel()], axis=1) + rng.uniform(-1, 1, (gx.size, 2)) * sc.pixel_scale
        if sc.star_density > 0:
            n_star = rng.poisson(sc.star_density * (2 * wx) * (2 * wy) / 3600.0)
            star = np.stack([rng.uniform(-wx + margin, wx - margin, n_star),
                             rng.uniform(-wy + margin, wy - margin, n_star)], axis=1)
        else:
            # stars in the middle of the grid's cells, clear of the galaxies' stamps' centres
            sx, sy = np.meshgrid(xs[:-1] + s / 2, ys[:-1] + s / 2, indexing="ij")
            star = np.stack([sx.ravel(), sy.ravel()], axis=1) + rng.uniform(-1, 1, (sx.size, 2)) * sc.pixel_scale
    else:
        area = (2 * wx) * (2 * wy) / 3600.0
        n_gal = rng.poisson(sc.galaxy_density * area)
        gal = np.stack([rng.uniform(-wx + margin, wx - margin, n_gal),
                        rng.uniform(-wy + margin, wy - margin, n_gal)], axis=1)
        n_star = rng.poisson(max(sc.star_density, 0.0) * area)
        star = np.stack([rng.uniform(-wx + margin, wx - margin, n_star),
                         rng.uniform(-wy + margin, wy - margin, n_star)], axis=1)
    return gal, star


# --------------------------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------------------------

def _magnitudes(sc, n, rng):
    """Magnitudes with dN/dm proportional to 10^(slope m) over mag_range (inverse CDF)."""
    a = sc.mag_slope * np.log(10.0)
    lo, hi = sc.mag_range
    u = rng.uniform(0, 1, n)
    return np.log(np.exp(a * lo) + u * (np.exp(a * hi) - np.exp(a * lo))) / a


def _galaxies(sc, n_pos, rng, fit_cfg):
    """Population draws (the paper's priors), sizes above ``max_scalelength`` redrawn; 90-degree pairs."""
    n_draw = (n_pos + 1) // 2 if sc.rotated_pairs else n_pos
    mags = _magnitudes(sc, n_draw, rng)
    pop = sample_population(mags, rng, fit_cfg)
    pop = {k: np.array(pop[k], copy=True) for k in ("scalelength", "bulge_fraction", "is_bulge", "e1", "e2")}
    for _ in range(100):
        big = pop["scalelength"] > sc.max_scalelength
        if not np.any(big):
            break
        redo = sample_population(mags[big], rng, fit_cfg)
        for k in pop:
            pop[k][big] = np.asarray(redo[k])[: int(big.sum())]
    pop["mag"] = mags
    if sc.rotated_pairs:
        pop = {k: np.repeat(v, 2)[:n_pos] for k, v in pop.items()}
        flip = np.arange(n_pos) % 2 == 1
        pop["e1"] = np.where(flip, -pop["e1"], pop["e1"])
        pop["e2"] = np.where(flip, -pop["e2"], pop["e2"])
    return pop


def _shears(sc, pos, rng):
    """Reduced shear (g1, g2) at each position: the constant, or the power-spectrum field."""
    if sc.shear_rms <= 0:
        return np.full(len(pos), sc.shear[0]), np.full(len(pos), sc.shear[1])
    wx, wy = _field_extent(sc)
    size = 2 * max(wx, wy) + 60.0
    ngrid = 64
    spacing = size / ngrid
    k0 = 2 * np.pi / size
    ps = galsim.PowerSpectrum(e_power_function=lambda k: (np.maximum(k, k0) / k0) ** -1.5, units=galsim.arcsec)
    ps.buildGrid(grid_spacing=spacing, ngrid=ngrid, rng=galsim.BaseDeviate(int(rng.integers(1, 2 ** 31))),
                 center=galsim.PositionD(0, 0))
    g1, g2 = ps.getShear([galsim.PositionD(float(x), float(y)) for x, y in pos])
    g1, g2 = np.atleast_1d(g1), np.atleast_1d(g2)
    scale = sc.shear_rms / max(np.sqrt(np.mean(g1 ** 2 + g2 ** 2) / 2), 1e-12)
    g1, g2 = g1 * scale, g2 * scale
    gm = np.hypot(g1, g2)
    clip = np.minimum(1.0, 0.3 / np.maximum(gm, 1e-12))
    return g1 * clip, g2 * clip


def _exposure_psf(sc, rng):
    """Per-exposure PSF parameters."""
    p = dict(fwhm=rng.uniform(*sc.psf_fwhm_range), beta=rng.uniform(*sc.psf_beta_range))
    e = sc.psf_e_max * np.sqrt(rng.uniform())
    phi = rng.uniform(0, np.pi)
    p["e1"], p["e2"] = e * np.cos(2 * phi), e * np.sin(2 * phi)
    if len(sc.psf_e_fixed):
        p["e1"], p["e2"] = (float(v) for v in sc.psf_e_fixed)
    p["gradient"] = rng.normal(0, 1, 4)
    # second suite: Kolmogorov seeing plus round optics
    p["defocus"] = rng.uniform(-0.4, 0.4)
    p["spher"] = rng.uniform(-0.2, 0.2)
    return p


def _psf_at(sc, p, u, v):
    """The PSF in the pixel frame (lengths in pixels) at field position (u, v) scaled to [-1, 1]."""
    wv = sc.psf_variation
    fwhm = p["fwhm"] * (1 + wv * (u * u + v * v) / 2) / sc.pixel_scale
    if sc.suite == "great":
        e1 = p["e1"] + wv * (p["gradient"][0] * u + p["gradient"][1] * v) / 2
        e2 = p["e2"] + wv * (p["gradient"][2] * u + p["gradient"][3] * v) / 2
        return galsim.Moffat(beta=p["beta"], fwhm=fwhm).shear(e1=e1, e2=e2)
    atm = galsim.Kolmogorov(fwhm=fwhm)
    # optics: 4 m class telescope at 800 nm, lambda/D in pixels
    lod = 800e-9 / 4.0 * 206265.0 / sc.pixel_scale
    opt = galsim.OpticalPSF(lam_over_diam=lod, defocus=p["defocus"], spher=p["spher"], obscuration=0.3)
    return galsim.Convolve(atm, opt)


# --------------------------------------------------------------------------------------------
# the field
# --------------------------------------------------------------------------------------------

def simulate_field(sc: SimulationConfig, out_dir, fit_cfg: FitConfig | None = None, progress=None) -> dict:
    """Write a simulated field to ``out_dir`` (see the module doc). Returns a summary dict."""
    fit_cfg = fit_cfg or FitConfig()
    os.makedirs(out_dir, exist_ok=True)
    rng = np.random.default_rng(sc.seed)
    gal_pos, star_pos = _positions(sc, rng)
    n_gal, n_star = len(gal_pos), len(star_pos)
    pop = _galaxies(sc, n_gal, rng, fit_cfg)
    g1, g2 = _shears(sc, gal_pos, rng)
    star_snr = np.exp(rng.uniform(*np.log(sc.star_snr_range), n_star))
    psfp = [_exposure_psf(sc, rng) for _ in range(sc.n_exposures)]
    gra, gdec = _to_radec(sc, gal_pos[:, 0], gal_pos[:, 1])
    sra, sdec = _to_radec(sc, star_pos[:, 0], star_pos[:, 1])
    wx, wy = _field_extent(sc)

    # noise: a point source of depth_mag has SNR 10 in the aperture, all exposures together
    med = galsim.Moffat(beta=np.mean(sc.psf_beta_range), fwhm=np.mean(sc.psf_fwhm_range) / sc.pixel_scale)
    ap_frac = _aperture_fraction(med)
    n_ap = np.pi * SNR_APERTURE ** 2
    sigma = mag_to_flux(sc.depth_mag) * ap_frac * np.sqrt(sc.n_exposures) / (10.0 * np.sqrt(n_ap))

    snr2 = np.zeros(n_gal)
    star_flux = np.zeros(n_star)
    specs = []
    gsp = galsim.GSParams(maximum_fft_size=8192)
    for k in range(sc.n_exposures):
        hdus, whdus, phdus = [fits.PrimaryHDU()], [fits.PrimaryHDU()], [fits.PrimaryHDU()]
        for c in range(sc.n_ccd):
            h = _ccd_header(sc, c, k)
            wcs = galsim.GSFitsWCS(header=h)
            img = galsim.ImageD(sc.ccd_nx, sc.ccd_ny, wcs=wcs)
            centre_psf = None
            for i in range(n_gal):
                pos = wcs.toImage(galsim.CelestialCoord(gra[i] * galsim.degrees, gdec[i] * galsim.degrees))
                if not (-20 < pos.x < sc.ccd_nx + 20 and -20 < pos.y < sc.ccd_ny + 20):
                    continue
                psf = _psf_at(sc, psfp[k], gal_pos[i, 0] / wx, gal_pos[i, 1] / wy)
                prof = galaxy_profile(pop["scalelength"][i], pop["bulge_fraction"][i], pop["e1"][i], pop["e2"][i],
                                      flux=mag_to_flux(pop["mag"][i]), g1=g1[i], g2=g2[i],
                                      is_bulge=bool(pop["is_bulge"][i]), truncation=fit_cfg.truncation,
                                      gsparams=gsp)
                conv = galsim.Convolve(wcs.local(pos).toImage(prof), psf, gsparams=gsp)
                n_st = int(min(256, max(48, 2 * np.ceil(6 * pop["scalelength"][i] / sc.pixel_scale) + 32)))
                stamp = conv.drawImage(nx=n_st, ny=n_st, scale=1.0, center=pos, method="auto")
                b = stamp.bounds & img.bounds
                if b.isDefined():
                    img[b] += stamp[b]
                if 1 <= pos.x <= sc.ccd_nx and 1 <= pos.y <= sc.ccd_ny:
                    snr2[i] += (_aperture_sum(stamp, pos) / (sigma * np.sqrt(n_ap))) ** 2
            for i in range(n_star):
                pos = wcs.toImage(galsim.CelestialCoord(sra[i] * galsim.degrees, sdec[i] * galsim.degrees))
                if not (-20 < pos.x < sc.ccd_nx + 20 and -20 < pos.y < sc.ccd_ny + 20):
                    continue
                psf = _psf_at(sc, psfp[k], star_pos[i, 0] / wx, star_pos[i, 1] / wy)
                # one flux per star, for the target SNR of a PSF-weighted (matched) measurement on the first
                # exposure that holds it; on the others its SNR follows their PSFs
                if star_flux[i] == 0:
                    star_flux[i] = star_snr[i] * sigma / np.sqrt(_psf_power(psf))
                st = psf.withFlux(star_flux[i]).drawImage(nx=48, ny=48, scale=1.0, center=pos, method="auto")
                b = st.bounds & img.bounds
                if b.isDefined():
                    img[b] += st[b]
            nrng = np.random.default_rng([sc.seed, k, c])
            data = img.array + sc.noise_sign * nrng.normal(0.0, sigma, img.array.shape)
            weight = np.full(data.shape, 1.0 / sigma ** 2, dtype=np.float32)
            _defects(sc, data, weight, nrng, sigma)
            hdus.append(fits.ImageHDU(data.astype(np.float32), header=h))
            whdus.append(fits.ImageHDU(weight, header=h))
            if sc.give_psf:
                # the PSF at the CCD centre in its pixel frame, 3x oversampled (docs/interface.rst: OVERSAMP = 3)
                cu = -((c - 0.5 * (sc.n_ccd - 1)) * (sc.ccd_nx + 20)) * sc.pixel_scale / wx   # CCDs run west
                centre_psf = _psf_at(sc, psfp[k], cu, 0.0)
                pim = galsim.Convolve(centre_psf, galsim.Pixel(1.0)).drawImage(
                    nx=144, ny=144, scale=1.0 / 3, method="no_pixel", use_true_center=False).array
                ph = fits.ImageHDU((pim / pim.sum()).astype(np.float64))
                ph.header["OVERSAMP"] = 3
                phdus.append(ph)
            if progress is not None:
                progress()
        _write_atomic(fits.HDUList(hdus), os.path.join(out_dir, f"exp{k}.fits"))
        _write_atomic(fits.HDUList(whdus), os.path.join(out_dir, f"exp{k}.weight.fits"))
        spec = {"image": f"exp{k}.fits", "weight": f"exp{k}.weight.fits"}
        if sc.give_psf:
            _write_atomic(fits.HDUList(phdus), os.path.join(out_dir, f"exp{k}.psf.fits"))
            spec["psf_true"] = f"exp{k}.psf.fits"
        specs.append(spec)

    snr = np.sqrt(snr2)
    ids = np.arange(n_gal + n_star)
    mag = np.concatenate([pop["mag"], ZERO_POINT - 2.5 * np.log10(np.maximum(star_flux, 1e-30))])
    is_star = np.concatenate([np.zeros(n_gal, bool), np.ones(n_star, bool)])
    ra = np.concatenate([gra, sra])
    dec = np.concatenate([gdec, sdec])
    truth = Table({
        "id": ids, "ra": ra, "dec": dec, "mag": mag,
        "g1": np.concatenate([g1, np.zeros(n_star)]), "g2": np.concatenate([g2, np.zeros(n_star)]),
        "e1_int": np.concatenate([pop["e1"], np.zeros(n_star)]),
        "e2_int": np.concatenate([pop["e2"], np.zeros(n_star)]),
        "scalelength": np.concatenate([pop["scalelength"], np.zeros(n_star)]),
        "bulge_fraction": np.concatenate([pop["bulge_fraction"], np.zeros(n_star)]),
        "is_bulge": np.concatenate([pop["is_bulge"].astype(bool), np.zeros(n_star, bool)]),
        "is_star": is_star,
        "snr": np.concatenate([snr, star_snr * np.sqrt(sc.n_exposures)]),
    })
    truth.meta["SEED"] = sc.seed
    truth.meta["SUITE"] = sc.suite
    truth.meta["SIGMA"] = sigma
    truth.meta["NOISESGN"] = sc.noise_sign
    # the measurement's catalogue: every object (a detection catalogue holds the stars too)
    _write_table(Table({"id": ids, "ra": ra, "dec": dec, "mag": mag}), os.path.join(out_dir, "objects.fits"))
    _write_table(Table({"id": ids[is_star], "ra": sra, "dec": sdec, "mag": mag[is_star]}),
                 os.path.join(out_dir, "stars.fits"))
    conf = {"exposures": [{k: v for k, v in s.items() if k != "psf_true"} for s in specs],
            "catalog": "objects.fits", "stars": "stars.fits", "output": "shear.fits"}
    conf.update(sc.fit_settings)
    _write_text(os.path.join(out_dir, "field.yaml"), yaml.safe_dump(conf, sort_keys=False))
    if sc.give_psf:
        conf_true = dict(conf, exposures=[{"image": s["image"], "weight": s["weight"], "psf": s["psf_true"]}
                                          for s in specs], output="shear_truepsf.fits")
        _write_text(os.path.join(out_dir, "field_truepsf.yaml"), yaml.safe_dump(conf_true, sort_keys=False))
    record = {k: (list(v) if isinstance(v, tuple) else v) for k, v in sc.__dict__.items()}
    _write_text(os.path.join(out_dir, "simulation.yaml"), yaml.safe_dump(record, sort_keys=False))
    # the truth last: a field with one is whole (simulate_missing resumes on it)
    _write_table(truth, os.path.join(out_dir, "truth.fits"))
    return dict(n_galaxies=n_gal, n_stars=n_star, sigma=sigma, config=os.path.join(out_dir, "field.yaml"),
                truth=os.path.join(out_dir, "truth.fits"), shear=(float(np.mean(g1)), float(np.mean(g2))))


def _aperture_fraction(psf):
    im = psf.drawImage(nx=64, ny=64, scale=1.0, method="auto").array
    c = np.arange(64) - 31.5
    ap = (c[:, None] ** 2 + c[None, :] ** 2) <= SNR_APERTURE ** 2
    return float(im[ap].sum() / im.sum())


def _aperture_sum(stamp, pos):
    """Noise-free counts of a stamp within SNR_APERTURE pixels of ``pos``."""
    b = stamp.bounds
    x = np.arange(b.xmin, b.xmax + 1) - pos.x
    y = np.arange(b.ymin, b.ymax + 1) - pos.y
    ap = (y[:, None] ** 2 + x[None, :] ** 2) <= SNR_APERTURE ** 2
    return float(stamp.array[ap].sum())


def _psf_power(psf):
    im = psf.drawImage(nx=48, ny=48, scale=1.0, method="auto").array
    im = im / im.sum()
    return float(np.sum(im * im))


def _defects(sc, data, weight, rng, sigma):
    """Bad columns and cosmic rays: corrupted pixels with weight 0."""
    ny, nx = data.shape
    for _ in range(int(sc.bad_columns)):
        x = int(rng.integers(0, nx))
        y0 = int(rng.integers(0, ny // 2))
        data[y0:, x] += 50 * sigma
        weight[y0:, x] = 0.0
    for _ in range(int(sc.cosmic_rays)):
        length = int(rng.integers(2, 12))
        x0, y0 = rng.uniform(0, nx), rng.uniform(0, ny)
        ang = rng.uniform(0, np.pi)
        t = np.linspace(0, length, 2 * length + 1)
        xs = np.clip(np.rint(x0 + t * np.cos(ang)).astype(int), 0, nx - 1)
        ys = np.clip(np.rint(y0 + t * np.sin(ang)).astype(int), 0, ny - 1)
        data[ys, xs] += rng.uniform(20, 200) * sigma
        weight[ys, xs] = 0.0


def _write_atomic(hdul, path):
    with atomic_path(path) as tmp:
        hdul.writeto(tmp, overwrite=True)


def _write_table(table, path):
    with atomic_path(path) as tmp:
        table.write(tmp, format="fits", overwrite=True)


def _write_text(path, text):
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(text)


def simulate_missing(job):
    """``(out_dir, mapping)``: simulate the field unless ``out_dir`` already holds its truth.fits (for
    resumable benchmark suites; picklable for process pools). Returns ``out_dir``."""
    out_dir, mapping = job
    if not os.path.exists(os.path.join(out_dir, "truth.fits")):
        simulate_field(simulation_config(mapping), out_dir)
    return out_dir


def truth_galaxies(paths, mag_range=(-np.inf, np.inf)) -> dict:
    """The galaxies (not stars) of simulated fields' ``truth.fits``, within ``mag_range``, sorted by magnitude.

    Returns a dict of arrays ``mag``, ``scalelength``, ``bulge_fraction``,
    ``is_bulge``, ``e1``, ``e2`` (the intrinsic ellipticity): the population of
    those fields, for benchmarks that draw the same galaxies another way (rings).
    """
    tabs = []
    for p in paths:
        t = Table.read(p)
        for col in ("mag", "scalelength", "bulge_fraction", "is_bulge", "e1_int", "e2_int", "is_star"):
            if col not in t.colnames:
                raise ShearfitValueError(f"{p}: no column {col} (not a truth table of shearfit simulate)")
        tabs.append(t)
    if not tabs:
        raise ShearfitValueError("no truth table given")
    t = vstack(tabs, metadata_conflicts="silent")
    mag = np.asarray(t["mag"], float)
    keep = ~np.asarray(t["is_star"], bool) & (mag >= mag_range[0]) & (mag <= mag_range[1])
    if keep.sum() < 2:
        raise ShearfitValueError(f"{', '.join(map(str, paths))}: fewer than 2 galaxies of magnitude "
                                 f"{mag_range[0]}-{mag_range[1]}")
    t = t[keep][np.argsort(mag[keep], kind="stable")]
    out = {name: np.asarray(t[col]) for name, col in (("mag", "mag"), ("scalelength", "scalelength"),
                                                       ("bulge_fraction", "bulge_fraction"), ("is_bulge", "is_bulge"),
                                                       ("e1", "e1_int"), ("e2", "e2_int"))}
    return out

