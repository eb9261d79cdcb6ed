"""Pixel PSF model on real stars: leave-one-out residuals and adaptive moments (issue 4, item 3).

Reads the DECam stars of one CCD from a SExtractor FITS_LDAC catalogue with
vignettes (``../shared/data/real/decam_00241238_01_stars.fits``: 117 stars,
exposure 241238, CCD 1), keeps those whose stamp has no masked pixel, and
for every star fits the pixel model (polynomial over the CCD) to all the
*other* stars, centres the held-out star on that model by cross-correlation
and compares:

* pixels: rms over the stamp of star/flux - model, against the rms that the
  star's own noise alone gives (sky SKYSIGMA plus Poisson with the gain), and
  the reduced chi^2 of the residual (1 when the model error is below the noise);
* adaptive moments (galsim.hsm.FindAdaptiveMom) of the star and of the model
  drawn at the star's sub-pixel position: ellipticity (distortion e1, e2) and
  size sigma; the scatter is set beside the one that noise alone produces
  (the model plus a noise realisation with the star's variance, measured the same way).

Because the held-out model is itself fitted to noisy stars, "residual at the
noise level" is not the right yardstick; the same test is therefore run on
a GalSim mirror of the catalogue: the same stars (positions, sub-pixel
offsets, fluxes, noise) drawn from a known smooth PSF (Moffat, beta 3.5, of
the stars' FWHM and mean ellipticity, with a linear ellipticity gradient
over the CCD), for which the model family is adequate. The real stars'
residuals beyond the mirror's are model error (PSF structure the pixel
model does not follow, the brighter-fatter effect, colour, blends).

Usage: python benchmarks/decam_stars.py [--size 21] [--orders 0 1 2 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import galsim
import numpy as np

from shearfit.psf.ldac import read_ldac_stars
from shearfit.psf.pixelmodel import _centre_by_xcorr, _star_fluxes, fit_pixel_psf, gaussian_centroid

DEFAULT = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "real", "decam_00241238_01_stars.fits")


OUTLIER_CHI2 = 6.0


def rsd(x):
    """Robust standard deviation (1.4826 MAD): a few failed moment measurements do not dominate it."""
    x = np.asarray(x)
    return 1.4826 * np.median(np.abs(x - np.median(x)))


def hsm(img, ivar=None):
    w = None if ivar is None else galsim.Image(np.ascontiguousarray(ivar))
    try:
        m = galsim.hsm.FindAdaptiveMom(galsim.Image(np.ascontiguousarray(img)), weight=w, strict=True)
    except galsim.GalSimHSMError:
        return np.nan, np.nan, np.nan
    return m.observed_shape.e1, m.observed_shape.e2, m.moments_sigma


def held_out(model, st1):
    """Centre one star on the model; return its flux-normalised image, the model at its position, flux."""
    D = np.fft.fft2(np.fft.ifftshift(st1.image, axes=(-2, -1)))
    cx, cy = gaussian_centroid(st1.image, 1.0, 2.0)
    st1.delta = np.stack([cx, cy], axis=1)
    st1.delta = _centre_by_xcorr(model, D, st1)
    flux, M = _star_fluxes(model, D, st1)
    mimg = np.fft.fftshift(np.fft.ifft2(M), axes=(-2, -1)).real[0]
    return st1.image[0] / flux[0], mimg, float(flux[0])


def mirror(stars, info, rng, pixel_scale=0.263, fwhm_px=None):
    """The same stars drawn by GalSim from a known smooth PSF, with the same noise model."""
    out = stars.subset(np.arange(len(stars)))
    n = stars.image.shape[-1]
    flux = np.array([s.sum() for s in stars.image])
    es1, es2, sig = np.nanmedian([hsm(im, iv) for im, iv in zip(stars.image, stars.ivar)], axis=0)
    # the Moffat's FWHM chosen so that its adaptive-moment size is the stars' median
    fwhm = 2.3548 * sig * pixel_scale
    for _ in range(3):
        probe = galsim.Moffat(beta=3.5, fwhm=fwhm).shear(e1=es1, e2=es2).drawImage(nx=n, ny=n, scale=pixel_scale)
        fwhm *= sig / hsm(probe.array)[2]
    imgs = []
    for i in range(len(stars)):
        e1 = es1 + 0.02 * stars.u[i]
        e2 = es2 - 0.02 * stars.v[i]
        psf = galsim.Moffat(beta=3.5, fwhm=fwhm).shear(e1=e1, e2=e2).withFlux(flux[i])
        im = psf.drawImage(nx=n, ny=n, scale=pixel_scale, offset=tuple(stars.delta[i])).array
        var = info["sky_sigma"] ** 2 + np.clip(im, 0, None) / info["gain"]
        imgs.append(im + rng.normal(size=im.shape) * np.sqrt(var))
        out.ivar[i] = 1.0 / var
    out.image = np.array(imgs)
    return out


def run(stars, order, rng, clip, native_width=1.0, iterations=2):
    n = len(stars)
    rows = []
    t0 = time.time()
    for i in range(n):
        others = np.ones(n, bool)
        others[i] = False
        model, _, _ = fit_pixel_psf(stars.subset(others), 1, order=order, iterations=iterations, clip=clip,
                                    native_width=native_width)
        st1 = stars.subset(np.array([i]))
        star, mimg, flux = held_out(model, st1)
        var = 1.0 / stars.ivar[i]
        r = star - mimg
        rms = np.sqrt(np.mean(r ** 2))
        noise = np.sqrt(np.mean(var)) / flux
        chi2 = np.mean(r ** 2 * flux ** 2 * stars.ivar[i])
        es = hsm(stars.image[i], stars.ivar[i])
        em = hsm(mimg * flux)
        en = hsm(mimg * flux + rng.normal(size=mimg.shape) * np.sqrt(var), stars.ivar[i])
        rows.append((rms, noise, chi2, *es, *em, *en, stars.snr[i], stars.x[i], stars.y[i]))
    rows = np.array(rows)
    dt = time.time() - t0
    return rows, dt


def summary(rows, label, dt):
    n = len(rows)
    outlier = rows[:, 2] > OUTLIER_CHI2
    rows = rows[~outlier]
    rms, noise, chi2 = rows[:, 0], rows[:, 1], rows[:, 2]
    es, em, en = rows[:, 3:6], rows[:, 6:9], rows[:, 9:12]
    ok = np.all(np.isfinite(rows[:, 3:12]), axis=1)
    d = (es - em)[ok]
    dn = (en - em)[ok]
    excess = np.sqrt(max(np.mean(rms ** 2) - np.mean(noise ** 2), 0.0))
    print(f"\n{label}: {n} leave-one-out fits in {dt:.1f} s; {int(outlier.sum())} held-out object(s) with reduced "
          f"chi^2 > {OUTLIER_CHI2:g} (a blend or galaxy) left out of the figures below")
    print(f"  residual rms per pixel / flux: {np.sqrt(np.mean(rms ** 2)):.2e} (median star {np.median(rms):.2e}); "
          f"star noise alone {np.sqrt(np.mean(noise ** 2)):.2e}; beyond the star's noise {excess:.1e}")
    snr = rows[:, 12]
    bright = snr > 100
    if bright.sum() > 3:
        eb = np.sqrt(max(np.mean(rms[bright] ** 2) - np.mean(noise[bright] ** 2), 0.0))
        print(f"  stars with SNR > 100 ({int(bright.sum())}): rms {np.sqrt(np.mean(rms[bright] ** 2)):.2e}, "
              f"noise {np.sqrt(np.mean(noise[bright] ** 2)):.2e}, beyond the noise {eb:.1e}")
    print(f"  reduced chi^2 of the residual: mean {np.mean(chi2):.3f}, median {np.median(chi2):.3f} "
          f"(1 = residual at the noise level)")
    print(f"  adaptive moments, {ok.sum()} stars: star e1 {np.mean(es[ok, 0]):+.4f}, e2 {np.mean(es[ok, 1]):+.4f}, "
          f"sigma {np.mean(es[ok, 2]):.3f} px")
    for j, name in enumerate(("e1", "e2")):
        print(f"    {name}: star - model mean {np.mean(d[:, j]):+.5f} +- {rsd(d[:, j]) / np.sqrt(len(d)):.5f}, "
              f"robust rms {rsd(d[:, j]):.5f}; noise alone {rsd(dn[:, j]):.5f}")
    rs = d[:, 2] / em[ok, 2]
    rn = dn[:, 2] / em[ok, 2]
    print(f"    sigma: (star - model)/model mean {np.mean(rs):+.5f} +- {rsd(rs) / np.sqrt(len(rs)):.5f}, "
          f"robust rms {rsd(rs):.5f}; noise alone {rsd(rn):.5f}")
    cc = [np.corrcoef(es[ok, j], em[ok, j])[0, 1] for j in range(2)]
    print(f"    star-to-star spread of e over the CCD: star e1 rms {np.std(es[ok, 0]):.4f}, model e1 rms "
          f"{np.std(em[ok, 0]):.4f}; corr(star, model) e1 {cc[0]:.2f}, e2 {cc[1]:.2f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--catalog", default=DEFAULT)
    ap.add_argument("--size", type=int, default=21, help="stamp side (odd), pixels")
    ap.add_argument("--orders", type=int, nargs="+", default=[0, 1, 2, 3], help="polynomial orders over the CCD")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clip", type=float, default=5.0, help="fit's outlier clip (robust sigmas; 0 = none)")
    ap.add_argument("--no-mirror", action="store_true", help="skip the GalSim mirror of the catalogue")
    ap.add_argument("--native-width", type=float, default=1.0,
                    help="relative width of the native model's prior (the pipeline's psf_native_width; 0: the paper's "
                         "plain least squares)")
    ap.add_argument("--iterations", type=int, default=2, help="the fit's centring rounds (psf_iterations)")
    args = ap.parse_args(argv)
    if not os.path.exists(args.catalog):
        sys.exit(f"{args.catalog}: no such file (pass --catalog)")
    rng = np.random.default_rng(args.seed)
    stars, info = read_ldac_stars(args.catalog, args.size)
    print(f"{args.catalog}: {info['n_rows']} stars, {len(info['masked'])} with a masked pixel in the "
          f"{args.size}x{args.size} stamp left out, {len(stars)} used; gain {info['gain']:.3f} e-/ADU, "
          f"sky sigma {info['sky_sigma']:.2f} ADU; SNR {np.min(stars.snr):.0f}-{np.max(stars.snr):.0f} "
          f"(median {np.median(stars.snr):.0f})")
    sims = None if args.no_mirror else mirror(stars, info, rng)
    for order in args.orders:
        rows, dt = run(stars, order, rng, args.clip, args.native_width, args.iterations)
        summary(rows, f"DECam stars, order {order}", dt)
        if sims is not None:
            rows, dt = run(sims, order, rng, args.clip, args.native_width, args.iterations)
            summary(rows, f"GalSim mirror (Moffat, known PSF), order {order}", dt)


if __name__ == "__main__":
    main()
