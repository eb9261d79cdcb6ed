#!/usr/bin/env python
"""Shear bias of the whole field pipeline: GalSim fields measured by ``shearfit measure``.

Writes two fields (shear +g and -g, same galaxies, PSFs, dithers and noise),
each of ``--n-exposures`` dithered exposures of ``--n-ccd`` CCDs with a TAN
(or rotated/flipped, or SIP-distorted) WCS, draws every galaxy with GalSim
through that WCS (its local affine map applied to the galaxy before the PSF,
which is defined in the pixel frame like a PSF model measured from stars),
gives the PSF as a FITS image per CCD, runs ``shearfit measure`` on each, and
prints m and c (rings of 4 orientations, bootstrap over rings) and the
pipeline's throughput.

    python benchmarks/field_test.py --n-galaxies 40                   # plain TAN
    python benchmarks/field_test.py --n-galaxies 40 --wcs rotated     # each exposure rotated, odd ones flipped
    python benchmarks/field_test.py --n-galaxies 40 --wcs distorted   # + a few per cent SIP distortion
    python benchmarks/field_test.py --wcs plain turned flipped        # the rotations alone, the flips alone
    python benchmarks/field_test.py --wcs plain rotated --layout inner  # every galaxy on every exposure in both
    python benchmarks/field_test.py --n-galaxies 40 --psf both        # PSF fitted from stars vs the true one
    python benchmarks/field_test.py --n-galaxies 40 --n-ccd 20 --spacing 96 --min-size 0.85 --max-extent 38
                                                                      # large galaxies, on grown stamps
    python benchmarks/field_test.py --wcs plain rotated distorted     # all three on the same galaxies, differences
    python benchmarks/field_test.py --psf both --psf-fwhm 0.36 0.38 --true-psf-oversampling 3 \
        --fitted-oversampling 1 3 --star-snr 200 2000                 # undersampled: native vs 3x fitted model
    python benchmarks/field_test.py --n-galaxies 320 --n-ccd 16 --metacal --antithetic --wcs distorted
                                      # metacal, each field with its antithetic twin (pixel and metacal noise negated)
    python benchmarks/field_test.py ... --seed 65 --table t65.fits    # the objects as a ring-test table, and
    python benchmarks/ring_split.py t64.fits t65.fits --unweighted    # several seeds' fields read as one

With ``--psf fitted`` or ``both`` every CCD also holds stars (a star
catalogue is given; at the default ``--spacing`` a star 31 pixels from a large galaxy blends with it:
``--spacing 64 --set psf_min_stars=20`` keeps them apart, 68 of 144 galaxies flagged blended against none
on 18 rings of 2 CCDs), each CCD of each exposure has its own PSF (a jump
between CCDs), and ``shearfit measure`` fits the pixel PSF models itself;
``both`` measures each field with the true PSF too and prints the
difference in m and c (same galaxies and noise, so most of the error cancels).
Several variants (WCS modes, fitted-model oversampling) are measured on the
same galaxies, and each is compared with the first.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import galsim
import numpy as np
import yaml
from astropy.io import fits
from astropy.table import Table

from shearfit.engine import priors
from shearfit.app.cli import main as shearfit_main
from shearfit.calib.bias import ring_sums, shear_bias
from shearfit.simulate.field import truth_galaxies
from shearfit.simulate.stamps import galaxy_profile, mag_to_flux
# benchmarks/ring_test.py, beside this script: the metacal columns, estimator and bootstrap
from ring_test import METACAL_FIELDS, MetacalRings, report_metacal, stars_kept

PIX = 0.187
RA0, DEC0 = 35.0, -4.0
NPIX = 512
SPACING = 44   # pixels between galaxies


def ccd_header(ccd, exposure, mode, rng_exp):
    """TAN header of CCD ``ccd`` in exposure ``exposure``: dithered, optionally rotated/flipped/SIP."""
    dx, dy = 7.3 * exposure, -4.1 * exposure           # a linear dither pattern, pixels
    angle = 0.0
    flip = 1.0
    if mode in ("rotated", "distorted", "turned"):
        angle = np.radians(23.0 + 41.0 * exposure)
    if mode in ("rotated", "distorted", "flipped"):
        flip = -1.0 if exposure % 2 else 1.0
    c, s = np.cos(angle), np.sin(angle)
    # north up, east left, then rotated about the reference pixel, odd exposures flipped in x
    cd = PIX / 3600.0 * np.array([[-c, s], [s, c]]) @ np.diag([flip, 1.0])
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = ("RA---TAN-SIP", "DEC--TAN-SIP") if mode == "distorted" else ("RA---TAN", "DEC--TAN")
    # the CCDs sit side by side on the sky; the reference point is the field centre
    off = (ccd - 0.5) * (NPIX + 20)
    h["CRVAL1"], h["CRVAL2"] = RA0, DEC0
    cx = NPIX / 2 - (np.linalg.inv(cd) @ np.array([-off * PIX / 3600.0, 0.0]))[0]
    cy = NPIX / 2 - (np.linalg.inv(cd) @ np.array([-off * PIX / 3600.0, 0.0]))[1]
    h["CRPIX1"], h["CRPIX2"] = cx + dx, cy + dy
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1]
    if mode == "distorted":
        # tangent point at the CCD's centre (as the CCD's own solution would have it), so that the
        # quadratic SIP terms change the scale by a few per cent across the CCD whatever its place
        from astropy.wcs import WCS

        ra_c, dec_c = WCS(h).all_pix2world([[NPIX / 2, NPIX / 2]], 1)[0]
        h["CRVAL1"], h["CRVAL2"] = float(ra_c), float(dec_c)
        h["CRPIX1"], h["CRPIX2"] = NPIX / 2, NPIX / 2
        h["A_ORDER"], h["B_ORDER"] = 2, 2
        h["A_2_0"], h["A_0_2"], h["A_1_1"] = 3e-5 * rng_exp[0], 2e-5 * rng_exp[1], 2e-5
        h["B_2_0"], h["B_0_2"], h["B_1_1"] = 2e-5 * rng_exp[2], 3e-5 * rng_exp[3], -2e-5
    h["MAGZP"], h["GAIN"], h["SATURATE"] = 30.0, 1.0, 1e9
    return h


def star_positions(args, rng):
    """Stars in the middle of the galaxy grid's cells (``--spacing``), so that their stamps avoid the galaxies: at
    the default spacing of 44 pixels they lie 31 pixels from four galaxies, where the co-added isophotes of
    the brightest stars and of the larger galaxies touch (fitclass -3); ``--spacing 64`` keeps them 45 apart
    (25 stars per CCD: give ``--set psf_min_stars=20`` too)."""
    nx_side = (NPIX - 2 * args.spacing) // args.spacing
    out = []
    for c in range(args.n_ccd):
        for i in range(nx_side - 1):
            for j in range(nx_side - 1):
                du = ((c - 0.5) * (NPIX + 20) + (i - nx_side / 2 + 1.0) * args.spacing + rng.uniform(-2, 2)) * PIX / 3600.0
                dv = ((j - nx_side / 2 + 1.0) * args.spacing + rng.uniform(-2, 2)) * PIX / 3600.0
                out.append((RA0 - du / np.cos(np.radians(DEC0)), DEC0 + dv, 10 ** rng.uniform(*np.log10(args.star_snr))))
    return np.array(out)


def draw(prof, n, pos, args):
    """``prof`` (in the pixel frame, without the pixel response) on an n x n stamp of unit pixels whose centre
    is nearest ``pos``: GalSim's drawImage (method "auto": its FFT holds the modes up to the pixels' Nyquist
    frequency or its maxk and drops those above instead of folding them), or with ``--sampled-rendering F``
    the pixel-convolved profile's values at the pixel centres, from a drawing F times finer of which every
    F-th pixel is kept: the sampling folds every mode up to F pi, as a detector's pixels do."""
    if not args.sampled_rendering:
        return prof.drawImage(nx=n, ny=n, scale=1.0, center=pos, method="auto")
    F = args.sampled_rendering
    ix, iy = int(np.floor(pos.x + 0.5)), int(np.floor(pos.y + 0.5))
    out = galsim.ImageD(galsim.BoundsI(ix - n // 2, ix - n // 2 + n - 1, iy - n // 2, iy - n // 2 + n - 1), scale=1.0)
    # fine pixel F i sits at native pixel xmin + i: the profile's centre at fine index F (pos - xmin)
    ox, oy = F * (pos.x - out.bounds.xmin) - F * (n // 2), F * (pos.y - out.bounds.ymin) - F * (n // 2)
    fine = galsim.Convolve(prof, galsim.Pixel(1.0), gsparams=args.gsparams).drawImage(
        nx=n * F, ny=n * F, scale=1.0 / F, method="no_pixel", offset=(ox, oy), use_true_center=False,
        dtype=np.float64).array
    out.array[:] = fine[::F, ::F] * F * F
    return out


def make_field(d, sign, args, gals, psfs, sigma, stars=None, with_psf=True, wcs_mode="plain", psf_settings=None,
               noise_sign=1):
    """Write one field (``sign`` of the shear) and its config; ``noise_sign`` -1 writes the antithetic twin: the
    same pixel noise negated."""
    g = sign * np.array(args.shear)
    specs = []
    rng_noise = np.random.default_rng(args.seed + 1000)   # the same noise for +g and -g
    for k in range(args.n_exposures):
        rng_exp = np.random.default_rng([args.seed, k]).uniform(0.5, 1.5, 4)
        hdus, whdus, phdus = [fits.PrimaryHDU()], [fits.PrimaryHDU()], []
        for c in range(args.n_ccd):
            h = ccd_header(c, k, wcs_mode, rng_exp)
            wcs = galsim.GSFitsWCS(header=h)
            img = galsim.ImageD(NPIX, NPIX, wcs=wcs)
            centre = wcs.toWorld(galsim.PositionD(NPIX / 2, NPIX / 2))
            reach = 0.75 * NPIX * PIX * galsim.arcsec   # beyond the CCD's corners: a SIP inverse may not converge
            for gal in gals:
                coord = galsim.CelestialCoord(gal["ra"] * galsim.degrees, gal["dec"] * galsim.degrees)
                if centre.distanceTo(coord) > reach:
                    continue
                pos = wcs.toImage(coord)
                if not (8 < pos.x < NPIX - 8 and 8 < pos.y < NPIX - 8):
                    continue
                local = wcs.local(pos)
                prof = galaxy_profile(gal["r"], gal["B"], gal["e1"], gal["e2"], flux=gal["flux"], g1=g[0], g2=g[1],
                                      is_bulge=gal["is_bulge"], gsparams=args.gsparams)
                conv = galsim.Convolve(local.toImage(prof), psfs[k][c], gsparams=args.gsparams)
                stamp = draw(conv, 64, pos, args)
                b = stamp.bounds & img.bounds
                img[b] += stamp[b]
            if stars is not None:
                pow_psf = float(np.sum(psfs[k][c].drawImage(nx=32, ny=32, scale=1.0).array ** 2))
                for ra, dec, snr in stars:
                    coord = galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)
                    if centre.distanceTo(coord) > reach:
                        continue
                    pos = wcs.toImage(coord)
                    if not (8 < pos.x < NPIX - 8 and 8 < pos.y < NPIX - 8):
                        continue
                    st = draw(psfs[k][c].withFlux(snr * sigma / np.sqrt(pow_psf)), 40, pos, args)
                    b = st.bounds & img.bounds
                    img[b] += st[b]
            noise = rng_noise.normal(0.0, sigma, (NPIX, NPIX))
            data = img.array + (0.0 if args.noise_free else noise_sign * noise)
            hdus.append(fits.ImageHDU(data, header=h))
            whdus.append(fits.ImageHDU(np.full((NPIX, NPIX), 1 / sigma ** 2, dtype=np.float32), header=h))
            os_k = args.true_psf_oversampling
            if os_k == 1 and args.sampled_rendering:
                pim = draw(psfs[k][c], 48, galsim.PositionD(24.0, 24.0), args).array   # centre at index 24
            elif os_k == 1:
                pim = psfs[k][c].drawImage(nx=48, ny=48, scale=1.0, method="auto", use_true_center=False).array
            else:
                # the pixel-convolved PSF sampled every 1/k pixel (docs/interface.rst: header OVERSAMP = k)
                pim = galsim.Convolve(psfs[k][c], galsim.Pixel(1.0)).drawImage(
                    nx=48 * os_k, ny=48 * os_k, scale=1.0 / os_k, method="no_pixel", use_true_center=False).array
            phdu = fits.ImageHDU(pim / pim.sum())
            phdu.header["OVERSAMP"] = os_k
            phdus.append(phdu)
        fits.HDUList(hdus).writeto(os.path.join(d, f"exp{k}.fits"), overwrite=True)
        fits.HDUList(whdus).writeto(os.path.join(d, f"exp{k}.weight.fits"), overwrite=True)
        fits.HDUList([fits.PrimaryHDU()] + phdus).writeto(os.path.join(d, f"exp{k}.psf.fits"), overwrite=True)
        specs.append({"image": f"exp{k}.fits", "weight": f"exp{k}.weight.fits"})
        if with_psf:
            specs[-1]["psf"] = f"exp{k}.psf.fits"
    cat = Table({"id": np.arange(len(gals)), "ra": [x["ra"] for x in gals], "dec": [x["dec"] for x in gals],
                 "mag": [x["mag"] for x in gals]})
    cat.write(os.path.join(d, "objects.fits"), overwrite=True)
    conf = {"exposures": specs, "catalog": "objects.fits"}
    if stars is not None:
        Table({"id": np.arange(len(stars)), "ra": stars[:, 0], "dec": stars[:, 1],
               "mag": 30 - 2.5 * np.log10(stars[:, 2])}).write(os.path.join(d, "stars.fits"), overwrite=True)
        conf["stars"] = "stars.fits"
    conf.update(psf_settings or {})
    with open(os.path.join(d, "field.yaml"), "w") as f:
        yaml.safe_dump(conf, f)
    return os.path.join(d, "field.yaml")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-galaxies", type=int, default=40, help="rings of 4 orientations")
    ap.add_argument("--n-exposures", type=int, default=7)
    ap.add_argument("--n-ccd", type=int, default=2)
    ap.add_argument("--wcs", choices=["plain", "rotated", "distorted", "turned", "flipped"], nargs="+",
                    default=["plain"],
                    help="one or more WCS variants of the same field; with several, the differences from the "
                         "first are printed with errors from the same rings resampled")
    ap.add_argument("--snr-min", type=float, default=100.0)
    ap.add_argument("--snr-max", type=float, default=200.0)
    ap.add_argument("--mag-min", type=float, default=21.0,
                    help="magnitudes drawn uniformly from --mag-min to --mag-max: the sizes from the prior at each "
                         "magnitude, the flux set by the SNR")
    ap.add_argument("--mag-max", type=float, default=24.0)
    ap.add_argument("--noise-sigma", type=float, default=None,
                    help="pixel sigma in counts at zero point 30, the flux the magnitude's (the SNR then follows "
                         "from magnitude and size, as on a survey field; the closure fields: 4.29) instead of unit "
                         "noise and the flux of a target SNR")
    ap.add_argument("--population-from", nargs="+", metavar="TRUTH",
                    help="the galaxies of simulated fields (truth.fits of shearfit simulate) within the magnitude "
                         "range, drawn at random with their magnitudes, instead of prior draws")
    ap.add_argument("--min-size", type=float, default=0.0, help="smallest scalelength drawn, arcsec")
    ap.add_argument("--max-size", type=float, default=np.inf, help="largest scalelength drawn, arcsec")
    ap.add_argument("--max-extent", type=float, default=20.0, metavar="PIX",
                    help="largest truncated model drawn, 4.5 scalelengths in pixels (default 20: every model fits "
                         "the 48-pixel stamp; raise it with --spacing to measure large galaxies on grown stamps)")
    ap.add_argument("--spacing", type=int, default=SPACING, help="pixels between galaxies on the grid")
    ap.add_argument("--noise-free", action="store_true", help="noise-free images, weights of the SNR range")
    ap.add_argument("--shear", type=float, nargs=2, default=[0.03, -0.02])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--antithetic", action="store_true",
                    help="also measure each field's antithetic twin (its pixel noise negated, and with --metacal "
                         "metacal's symmetrising noise too: metacal_noise_sign=-1): the twin's objects join their "
                         "rings, and the terms odd in the noise cancel within each ring")
    ap.add_argument("--metacal", action="store_true",
                    help="measure with calibration: metacal and report the metacal shear bias (<R>^-1 <e> per sign) "
                         "beside lensfit's on the noshear images")
    ap.add_argument("--n-bootstrap", type=int, default=500, help="bootstrap resamplings of the rings")
    ap.add_argument("--processes", type=int, default=os.cpu_count())
    ap.add_argument("--keep", default=None, help="keep the fields in this directory")
    ap.add_argument("--psf", choices=["given", "fitted", "both"], default="given",
                    help="measure with the true PSF (given), one fitted from stars, or both")
    ap.add_argument("--fitted-oversampling", type=int, nargs="+", default=None,
                    help="with --psf fitted/both: one fitted-PSF run per oversampling factor (e.g. 1 3)")
    ap.add_argument("--star-snr", type=float, nargs=2, default=[50.0, 1000.0],
                    help="range of the stars' integrated SNR per exposure (log-uniform)")
    ap.add_argument("--accurate-rendering", action="store_true",
                    help="GalSim folding_threshold 1e-3, maxk_threshold 1e-4 (defaults 5e-3, 1e-3)")
    ap.add_argument("--sampled-rendering", type=int, default=0, metavar="F",
                    help="draw galaxies, stars and native PSF images as the pixel-convolved profiles' values at "
                         "the pixel centres, from a drawing F times finer (the sampling folds the modes above "
                         "Nyquist, which GalSim's drawImage at the pixel scale drops); 0: drawImage")
    ap.add_argument("--psf-e-max", type=float, default=0.07,
                    help="PSF ellipticity components drawn uniformly in +-this per exposure (0: round PSFs)")
    ap.add_argument("--psf-fwhm", type=float, nargs=2, default=[0.5, 0.8], help="range of PSF FWHM, arcsec")
    ap.add_argument("--true-psf-oversampling", type=int, default=1,
                    help="samples per pixel of the true PSF given to the 'given' runs (odd; 3 for undersampled PSFs)")
    ap.add_argument("--layout", choices=["grid", "inner"], default="grid",
                    help="grid: the whole galaxy grid of each CCD; inner: only the slots within 176 pixels of "
                         "the CCD centre, whose stamps stay on the CCD in every exposure whatever its rotation "
                         "and dither, so every WCS variant observes every galaxy on every exposure")
    ap.add_argument("--size-split", type=_edges, default=None, metavar="R[,R2,...]",
                    help="also print m and c for the rings of true scalelength below and above R arcsec (several "
                         "comma-separated edges: below the first, between each two, and above the last)")
    ap.add_argument("--reuse", action="store_true",
                    help="with --keep: read the catalogue of a field already measured there (same options) "
                         "instead of simulating and measuring it again")
    ap.add_argument("--table", default=None, metavar="FILE",
                    help="write the measured objects as a ring-test table (benchmarks/ring_test.py --out's columns), "
                         "for benchmarks/ring_split.py to read several runs (seeds) as one; with several variants, "
                         "one file each, the variant's name before the extension")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="setting of every run (e.g. psf_oversampling=3 for the fitted-PSF runs, or an engine "
                         "setting such as size_prior_axis=area)")
    args = ap.parse_args(argv)
    args.gsparams = (galsim.GSParams(folding_threshold=1e-3, maxk_threshold=1e-4)
                     if args.accurate_rendering else None)
    args.psf_settings = {kv.split("=", 1)[0]: yaml.safe_load(kv.split("=", 1)[1]) for kv in args.set}
    rng = np.random.default_rng(args.seed)
    sigma = 1.0 if args.noise_sigma is None else float(args.noise_sigma)
    replay = truth_galaxies(args.population_from, (args.mag_min, args.mag_max)) if args.population_from else None
    base = [(rng.uniform(2.5, 4.5), rng.uniform(*args.psf_fwhm) / PIX, args.psf_e_max * rng.uniform(-1, 1),
             args.psf_e_max * rng.uniform(-1, 1)) for _ in range(args.n_exposures)]
    # with stars, each CCD has its own PSF (a jump at the CCD boundary); otherwise one per exposure
    jump = 0.0 if args.psf == "given" else 1.0
    psfs = [[galsim.Moffat(beta=b, fwhm=f * (1 + 0.04 * jump * c)).shear(g1=g1 + 0.015 * jump * c,
                                                                         g2=g2 - 0.01 * jump * c)
             for c in range(args.n_ccd)] for b, f, g1, g2 in base]
    stars = star_positions(args, np.random.default_rng(args.seed + 7)) if args.psf != "given" else None
    # galaxies on a grid over the CCDs (the dithers move them by < 30 pixels)
    nx_side = (NPIX - 2 * args.spacing) // args.spacing
    slots = [(c, i, j) for c in range(args.n_ccd) for i in range(nx_side) for j in range(nx_side)]
    if args.layout == "inner":
        # the largest dither moves a CCD by 50 pixels and a stamp reaches 24 beyond its centre: a slot
        # within 176 pixels of the centre keeps its stamp 6 pixels inside the CCD at any rotation
        slots = [(c, i, j) for c, i, j in slots
                 if np.hypot(i - nx_side / 2 + 0.5, j - nx_side / 2 + 0.5) * args.spacing <= 176.0]
    if 4 * args.n_galaxies > len(slots):
        raise SystemExit(f"at most {len(slots) // 4} rings fit on {args.n_ccd} CCDs")
    order = rng.permutation(len(slots))
    gals = []
    pop_mags = rng.uniform(args.mag_min, args.mag_max, 4 * args.n_galaxies)
    k = 0
    while len(gals) < 4 * args.n_galaxies:
        p = priors.sample_population(np.array([pop_mags[k % pop_mags.size]]), rng)[0]
        if replay is not None:
            i = int(rng.integers(0, replay["mag"].size))
            p = {name: replay[name][i] for name in replay}
        k += 1
        if (p["scalelength"] < args.min_size or p["scalelength"] > args.max_size
                or 4.5 * p["scalelength"] / PIX > args.max_extent):
            continue
        snr = rng.uniform(args.snr_min, args.snr_max)
        e = complex(p["e1"], p["e2"])
        for j in range(4):
            c, ix, iy = slots[order[len(gals)]]
            du = ((c - 0.5) * (NPIX + 20) + (ix - nx_side / 2 + 0.5) * args.spacing) * PIX / 3600.0
            dv = (iy - nx_side / 2 + 0.5) * args.spacing * PIX / 3600.0
            ej = e * np.exp(1j * np.pi * j / 2)
            gals.append(dict(ring=len(gals) // 4, ra=RA0 - du / np.cos(np.radians(DEC0)), dec=DEC0 + dv,
                             r=float(p["scalelength"]), B=float(p["bulge_fraction"]), is_bulge=bool(p["is_bulge"]),
                             e1=ej.real, e2=ej.imag, mag=float(p["mag"]), snr=snr))
    # flux for the target SNR (profile-weighted, all exposures) at pixel noise sigma, or the magnitude's
    for gal in gals:
        if args.noise_sigma is not None:
            gal["flux"] = float(mag_to_flux(gal["mag"]))
            continue
        prof = galaxy_profile(gal["r"], gal["B"], gal["e1"], gal["e2"], flux=1.0, is_bulge=gal["is_bulge"])
        power = sum(float(np.sum(galsim.Convolve(prof.dilate(1 / PIX), p[0]).drawImage(nx=64, ny=64, scale=1.0)
                                 .array ** 2)) for p in psfs)
        gal["flux"] = gal["snr"] * sigma / np.sqrt(power)
    fitted = [("fitted", False, dict(args.psf_settings))]
    if args.fitted_oversampling:
        fitted = [(f"fitted {k}x", False, {**args.psf_settings, "psf_oversampling": k}) for k in args.fitted_oversampling]
    given = [("given", True, dict(args.psf_settings))]
    psf_variants = {"given": given, "fitted": fitted, "both": given + fitted}[args.psf]
    # every (WCS, PSF) combination of the same galaxies, PSFs and noise
    variants = [(w, name, with_psf) for w in args.wcs for name, with_psf, _ in psf_variants]
    settings = {name: st for name, _, st in psf_variants}
    label = {v: (v[1] if len(args.wcs) == 1 else f"{v[0]} WCS, {v[1]}") for v in variants}
    tables = {}
    args.psf_sky = {}   # per WCS variant: its exposures' given PSFs in the sky frame (exposure_psfs)
    twins = (+1, -1) if args.antithetic else (+1,)
    t_meas = 0.0
    n_meas = 0
    with tempfile.TemporaryDirectory() as tmp:
        base_dir = args.keep or tmp
        for sign, twin in [(s, t) for s in (+1, -1) for t in twins]:
            for v in variants:
                wcs_mode, name, with_psf = v
                d = os.path.join(base_dir, ("plus" if sign > 0 else "minus") + ("_twin" if twin < 0 else "") +
                                 ("" if len(variants) == 1 else f"_{wcs_mode}_{name.replace(' ', '')}"))
                os.makedirs(d, exist_ok=True)
                out = os.path.join(d, "shear.fits")
                what = f"{'+g' if sign > 0 else '-g'}{', twin' if twin < 0 else ''}"
                if args.reuse and os.path.exists(out):
                    tables[(v, sign, twin)] = Table.read(out)
                    print(f"field {what} ({label[v]}): read from {out}", flush=True)
                else:
                    t0 = time.perf_counter()
                    run_settings = dict(settings[name])
                    if args.metacal:
                        run_settings["calibration"] = "metacal"
                        if twin < 0:
                            run_settings["metacal_noise_sign"] = -1
                    cfgpath = make_field(d, sign, args, gals, psfs, sigma, stars=stars, with_psf=with_psf,
                                         wcs_mode=wcs_mode, psf_settings=run_settings, noise_sign=twin)
                    t_sim = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    rc = shearfit_main(["measure", cfgpath, "--out", out, "--quiet", "-j", str(args.processes)])
                    t_meas += time.perf_counter() - t0
                    n_meas += len(gals)
                    if rc != 0:
                        raise SystemExit(f"shearfit measure failed ({rc})")
                    tables[(v, sign, twin)] = Table.read(out)
                    print(f"field {what} ({label[v]}): simulated in {t_sim:.0f} s, measured in "
                          f"{time.perf_counter() - t0:.0f} s", flush=True)
                if with_psf and wcs_mode not in args.psf_sky:
                    # each WCS its own: rotated and distorted exposures carry the PSF to the sky differently
                    args.psf_sky[wcs_mode] = exposure_psfs(d, args.n_exposures)
    if n_meas:
        print(f"\nshearfit measure: {n_meas / t_meas / args.processes:.2f} objects/s per process "
              f"({args.processes} processes, PSF fitting included where fitted)")
    results = {}
    for v in variants:
        fields = {k[1:]: t for k, t in tables.items() if k[0] == v}
        if args.table:   # (before the report: the measured objects kept whatever it does)
            path = args.table
            if len(variants) > 1:
                root, ext = os.path.splitext(args.table)
                path = f"{root}_{label[v].replace(' ', '').replace(',', '_')}{ext or '.fits'}"
            ring_table(fields, gals, args).write(path, overwrite=True)
            print(f"  objects written to {path} (benchmarks/ring_split.py reads it)")
        results[label[v]] = report(fields, gals, args, label[v], v[0])
    if len(variants) > 1:
        # differences from the first variant, resampling the same rings for all
        rng_b = np.random.default_rng(0)
        g = np.array(args.shear)
        sums = {v: ring_sums(_rows({k[1:]: t for k, t in tables.items() if k[0] == v}, gals), args.n_galaxies)
                for v in variants}
        ref = variants[0]
        subsets = [("", np.arange(args.n_galaxies))] + [(f" (rings of scalelength {what})", rings)
                                                         for what, rings in size_subsets(gals, args)]
        for v in variants[1:]:
            for what, rings in subsets:
                picks = [rings[rng_b.integers(0, rings.size, rings.size)] for _ in range(300)]
                diff = [shear_bias(sums[v][:, pick], g, 2, rng_b)[0] - shear_bias(sums[ref][:, pick], g, 2, rng_b)[0]
                        for pick in picks]
                err = np.std(diff, axis=0)
                d0 = shear_bias(sums[v][:, rings], g, 2, rng_b)[0] - shear_bias(sums[ref][:, rings], g, 2, rng_b)[0]
                print(f"\n{label[v]} minus {label[ref]}{what}: dm1 = {d0[0]:+.5f} +/- {err[0]:.5f}, "
                      f"dm2 = {d0[1]:+.5f} +/- {err[1]:.5f}, dc1 = {d0[2]:+.6f} +/- {err[2]:.6f}, "
                      f"dc2 = {d0[3]:+.6f} +/- {err[3]:.6f}")
    return results


def _rows(tables, gals):
    """The objects of every field as one table: ``tables`` maps (sign, twin) to a catalogue (the twin's objects
    are more members of their rings); the metacal columns come along where the catalogues have them."""
    cols = ("e1", "e2", "e_var", "weight", "iso_weight", "fitclass", "m") + METACAL_FIELDS
    rows = {k: [] for k in ("galaxy", "sign", "twin") + cols}
    for (sign, twin), t in tables.items():
        for gal, row in zip(gals, t):
            rows["galaxy"].append(gal["ring"])
            rows["sign"].append(sign)
            rows["twin"].append(twin)
            for key in cols:
                rows[key].append(row[key] if key in t.colnames else np.nan)
    return {k: np.array(v) for k, v in rows.items()}


def ring_table(tables, gals, args):
    """The objects of every field in ``benchmarks/ring_test.py --out``'s form: ring (``galaxy``), the shear's
    ``sign``, ``rotation`` (0-3, the twin's 4-7), the shear (``g1``, ``g2``, signed), the truth and the
    catalogue's measurement (with a metacal run's versions and R columns), so that ``ring_split.py`` reads the runs
    of several seeds as one, and ``ring_test.py --from-tables ... --metacal`` their metacal m (``--paired-with``
    another run's tables of the same fields: the two runs' difference)."""
    tab = _rows(tables, gals)
    index = np.concatenate([np.arange(len(gals))] * len(tables))
    truth = {key: np.array([gals[i][src] for i in index]) for key, src in
             (("e1_int", "e1"), ("e2_int", "e2"), ("true_scalelength", "r"), ("true_bulge_fraction", "B"))}
    g = np.array(args.shear, float)
    out = Table({"galaxy": tab["galaxy"].astype(np.int64), "sign": tab["sign"].astype(np.int64),
                 "rotation": (index % 4 + np.where(tab["twin"] < 0, 4, 0)).astype(np.int64),
                 "g1": tab["sign"] * g[0], "g2": tab["sign"] * g[1], **truth})
    for key in ("fitclass", "e1", "e2", "e_var", "weight", "iso_weight"):
        out[key] = tab[key]
    out["fitclass"] = np.nan_to_num(out["fitclass"], nan=-1).astype(np.int64)
    fields = list(tables.values())
    for key in ("flux_snr", "snr", "scalelength", "round_scalelength"):
        if all(key in t.colnames for t in fields):
            out[key] = np.concatenate([np.asarray(t[key], float) for t in fields])
    # a metacal run's versions and responses (``ring_test.py --from-tables ... --metacal``, and ``--paired-with``
    # another run of the same fields)
    if all(all(key in t.colnames for key in METACAL_FIELDS) for t in fields):
        for key in METACAL_FIELDS:
            out[key] = (np.nan_to_num(tab[key], nan=-1).astype(np.int64) if key.startswith("fitclass")
                        else np.asarray(tab[key], float))
    return out


def _edges(text):
    """``--size-split``'s edges: one number or several, comma-separated, increasing."""
    try:
        edges = [float(x) for x in str(text).split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or a comma-separated list of numbers: {text!r}") from None
    if any(b <= a for a, b in zip(edges[:-1], edges[1:])):
        raise argparse.ArgumentTypeError(f"the edges must increase: {text!r}")
    return edges


def size_subsets(gals, args):
    """With ``--size-split R[,R2,...]``: (label, ring indices) of the rings of true scalelength below the first
    edge, between each two and at or above the last.

    A choice on the truth, the same for the 8 objects of a ring; subsets of fewer than 2 rings are left out.
    """
    if not args.size_split:
        return []
    r = np.array([gals[4 * k]["r"] for k in range(args.n_galaxies)])
    edges = list(args.size_split)
    out = [(f"< {edges[0]}\"", r < edges[0])]
    out += [(f"{a}-{b}\"", (r >= a) & (r < b)) for a, b in zip(edges[:-1], edges[1:])]
    out.append((f">= {edges[-1]}\"", r >= edges[-1]))
    return [(lab, np.flatnonzero(sel)) for lab, sel in out if sel.sum() > 1]


def exposure_psfs(d, n_exposures):
    """Per exposure of the field in ``d``, its given PSF on its first CCD as the catalogue's psf_e1, psf_e2 and
    psf_fwhm measure it (adaptive moments carried to the sky by the local Jacobian at the CCD's centre): rows
    (e1, e2, FWHM arcsec)."""
    import warnings

    from astropy.wcs import WCS, FITSFixedWarning

    from shearfit.io.wcs import local_jacobian
    from shearfit.pipeline.driver import psf_ellipticity, psf_fwhm_arcsec, psf_moments

    rows = []
    for e in range(n_exposures):
        with fits.open(os.path.join(d, f"exp{e}.fits")) as im, fits.open(os.path.join(d, f"exp{e}.psf.fits")) as ps:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", FITSFixedWarning)
                w = WCS(im[1].header)
            ny, nx = im[1].data.shape
            J = np.asarray(local_jacobian(w, nx / 2, ny / 2), float).reshape(2, 2)
            k = int(ps[1].header.get("OVERSAMP", 1))
            m = psf_moments(ps[1].data)
            rows.append(psf_ellipticity(ps[1].data, J, k, moments=m) + (psf_fwhm_arcsec(J, k, moments=m),))
    return np.array(rows, float)


def report(tables, gals, args, name, wcs_mode):
    tab = _rows(tables, gals)
    est, err = shear_bias(ring_sums(tab, args.n_galaxies), np.array(args.shear), args.n_bootstrap,
                          np.random.default_rng(0))
    fc = tab["fitclass"]
    print(f"\n[{name} PSF] {args.n_galaxies} rings x 4{' x 2 twins' if args.antithetic else ''} x 2 shears, "
          f"{args.n_exposures} exposures x {args.n_ccd} CCDs, "
          f"WCS {wcs_mode}, "
          f"{f'noise sigma {args.noise_sigma:g}' if args.noise_sigma else f'SNR {args.snr_min:.0f}-{args.snr_max:.0f}'}"
          f"{' (noise-free)' if args.noise_free else ''}, "
          f"scalelength >= {args.min_size}\"")
    print(f"  m1 = {est[0]:+.5f} +/- {err[0]:.5f}    c1 = {est[2]:+.6f} +/- {err[2]:.6f}")
    print(f"  m2 = {est[1]:+.5f} +/- {err[1]:.5f}    c2 = {est[3]:+.6f} +/- {err[3]:.6f}")
    sky = getattr(args, "psf_sky", {}).get(wcs_mode)
    if sky is not None:
        # a PSF leakage alpha makes c = alpha e_psf, e_psf the exposures' PSF ellipticity as the fits weigh them:
        # for small galaxies the sharpest exposures count most (about as FWHM^-4)
        g, w = sky[:, :2], sky[:, 2] ** -4.0
        gw = w @ g / w.sum()
        print(f"  the exposures' given PSFs (sky frame, adaptive moments, CCD 1): ellipticity mean ({g[:, 0].mean():+.4f}, "
              f"{g[:, 1].mean():+.4f}), weighted by FWHM^-4 ({gw[0]:+.4f}, {gw[1]:+.4f}); FWHM {sky[:, 2].min():.2f}-"
              f"{sky[:, 2].max():.2f}\"")
        gg = float(gw @ gw)
        if gg > 0.005 ** 2:
            # c's component along the weighted PSF ellipticity, as a leakage: alpha = c . e_psf / |e_psf|^2
            alpha = (est[2] * gw[0] + est[3] * gw[1]) / gg
            alpha_err = float(np.hypot(err[2] * gw[0], err[3] * gw[1])) / gg
            print(f"  c along the weighted PSF ellipticity: alpha = {alpha:+.4f} +/- {alpha_err:.4f}")
    good = (fc == 0) & np.isfinite(tab["m"]) & (np.nan_to_num(tab["weight"]) > 0)
    if good.any():
        # the catalogue's m column (the calibration in force, shearfit's default unless --set calibration=...)
        mbar = float(np.sum(tab["weight"][good] * tab["m"][good]) / np.sum(tab["weight"][good]))
        cal, cal_err = (1 + est[:2]) / (1 + mbar) - 1, err[:2] / (1 + mbar)
        print(f"  calibrated by the catalogue's m (weighted mean {mbar:+.4f}): m1 = {cal[0]:+.5f} +/- "
              f"{cal_err[0]:.5f}, m2 = {cal[1]:+.5f} +/- {cal_err[1]:.5f}")
    print("  fitclass: " + ", ".join(f"{int((fc == v).sum())} x {v}" for v in np.unique(fc)))
    lost = (fc != 0) & (fc != 1)
    if np.any(lost):
        # a flagged or failed object counts with zero weight, as in a catalogue, and so breaks its ring (the
        # others' intrinsic shapes no longer cancel): m on the other rings, and where the lost objects were
        out = np.unique(tab["galaxy"][lost])
        whole = np.setdiff1d(np.arange(args.n_galaxies), out)
        e_w, r_w = shear_bias(ring_sums(tab, args.n_galaxies)[:, whole], np.array(args.shear), args.n_bootstrap,
                              np.random.default_rng(0))
        sign = tab["sign"]
        print(f"  whole rings only ({out.size} rings with a flagged or failed object left out; those objects "
              f"{int(np.sum(lost & (sign > 0)))} at +g, {int(np.sum(lost & (sign < 0)))} at -g): "
              f"m1 = {e_w[0]:+.5f} +/- {r_w[0]:.5f}, m2 = {e_w[1]:+.5f} +/- {r_w[1]:.5f}")
    if np.any(fc == 1):
        # the star/galaxy test selects on shape (an elongated small galaxy beats a point source by more), and
        # so on the shear: the same objects with those classified as stars kept, at the weight of their e_var
        star = fc == 1
        kept = stars_kept(tab)
        est_s, err_s = shear_bias(ring_sums(kept, args.n_galaxies), np.array(args.shear), args.n_bootstrap,
                                  np.random.default_rng(0))
        print(f"  without the star/galaxy selection ({int(star.sum())} objects classified as stars kept): "
              f"m1 = {est_s[0]:+.5f} +/- {err_s[0]:.5f}, m2 = {est_s[1]:+.5f} +/- {err_s[1]:.5f}")
    # weights that do not respond to the shear (lensfit's do, for small galaxies): unit weights for the
    # galaxies, and the catalogue's iso_weight (each galaxy's bin mean of lensfit's weight)
    others = [("unit weights (fitclass 0)", np.where(fc == 0, 1.0, 0.0))]
    if np.any(np.nan_to_num(tab["iso_weight"]) > 0):
        others.append(("the catalogue's iso_weight", np.nan_to_num(tab["iso_weight"])))
    other_sums = []
    for label, w in others:
        other_sums.append(ring_sums(dict(tab, weight=w), args.n_galaxies))
        est_u, err_u = shear_bias(other_sums[-1], np.array(args.shear), args.n_bootstrap, np.random.default_rng(0))
        print(f"  with {label}: m1 = {est_u[0]:+.5f} +/- {err_u[0]:.5f}, m2 = {est_u[1]:+.5f} +/- {err_u[1]:.5f}")
    if args.metacal:
        _report_metacal(Table(tab), args, args.n_galaxies)
    subsets = size_subsets(gals, args)
    if subsets:
        sums = ring_sums(tab, args.n_galaxies)
        for lab, sel in subsets:
            e_s, r_s = shear_bias(sums[:, sel], np.array(args.shear), args.n_bootstrap, np.random.default_rng(0))
            print(f"  rings of scalelength {lab} ({sel.size}): m1 = {e_s[0]:+.5f} +/- {r_s[0]:.5f}, "
                  f"m2 = {e_s[1]:+.5f} +/- {r_s[1]:.5f}, c1 = {e_s[2]:+.6f} +/- {r_s[2]:.6f}, "
                  f"c2 = {e_s[3]:+.6f} +/- {r_s[3]:.6f}")
            for (label, _), o_sums in zip(others, other_sums):
                e_u, r_u = shear_bias(o_sums[:, sel], np.array(args.shear), args.n_bootstrap,
                                      np.random.default_rng(0))
                print(f"    with {label}: m1 = {e_u[0]:+.5f} +/- {r_u[0]:.5f}, m2 = {e_u[1]:+.5f} +/- "
                      f"{r_u[1]:.5f}")
        if args.metacal:
            for lab, sel in subsets:
                # the subset's rings renumbered 0 .. n - 1, for the metacal report's bootstrap over rings
                number = np.full(args.n_galaxies, -1)
                number[sel] = np.arange(sel.size)
                rows = number[tab["galaxy"]] >= 0
                sub = Table({k: v[rows] for k, v in tab.items()})
                sub["galaxy"] = number[tab["galaxy"][rows]]
                print(f"\n  rings of scalelength {lab} ({sel.size}), metacal:", end="")
                _report_metacal(sub, args, sel.size)
    return est, err


def _report_metacal(tab, args, n_gal):
    """ring_test.py's metacal report of a field's objects (``tab``, galaxies numbered 0 .. n_gal - 1): lensfit's
    weights and selection, no split by SNR."""
    margs = argparse.Namespace(**{**vars(args), "all_objects": False, "unweighted": False, "snr_bins": 1})
    report_metacal(MetacalRings.from_table(tab, n_gal, margs), margs, by_snr=False)


if __name__ == "__main__":
    main()
