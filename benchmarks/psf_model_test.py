#!/usr/bin/env python
"""The pixel PSF model against the true PSF (issue 4, item 1).

GalSim stars (elliptical Moffat, FWHM and ellipticity varying smoothly over
a 2-CCD field with a jump between the CCDs, random sub-pixel centres,
integrated SNR log-uniform from --snr-min to 1000, catalogue positions off
by a smooth astrometric error per CCD) are fitted by
``shearfit.psf.fit_pixel_psf``; at 50 random positions the model is compared
with the true pixel-convolved PSF (sampled at the model's resolution).
Prints the rms pixel residual relative to the flux, the ellipticity and size
residuals (adaptive moments) and the registration error.

    python benchmarks/psf_model_test.py --n-stars 600
    python benchmarks/psf_model_test.py --fwhm 0.374 --oversampling 3    # undersampled PSF, 3x model
"""

import argparse
import time

import galsim
import numpy as np

from shearfit.psf.pixelmodel import StarSet, fit_pixel_psf

PIX = 0.187


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-stars", type=int, default=600)
    ap.add_argument("--snr-min", type=float, default=50.0)
    ap.add_argument("--fwhm", type=float, default=0.7, help="PSF FWHM at the field centre, arcsec")
    ap.add_argument("--oversampling", type=int, default=1)
    ap.add_argument("--order", type=int, default=3)
    ap.add_argument("--size", type=int, default=25)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--alias-width", type=float, default=0.5, help="relative width of the above-Nyquist prior")
    ap.add_argument("--native-width", type=float, default=1.0,
                    help="relative width of the native model's prior (0: plain least squares, the paper's fit)")
    ap.add_argument("--iterations", type=int, default=2,
                    help="rounds of star centring and refitting after the first fit (the pipeline's psf_iterations)")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    n, k = a.size, a.oversampling

    def psf_at(ccd, u, v):
        fwhm = a.fwhm * (1 + 0.08 * u * u + 0.05 * v) + 0.02 * ccd
        e1 = 0.03 + 0.04 * u - 0.02 * v * v + 0.01 * ccd
        e2 = -0.02 + 0.03 * v + 0.02 * u * v
        return galsim.Moffat(beta=3.0, fwhm=fwhm).shear(e1=e1, e2=e2)

    def draw(p, dx, dy, step=1):
        im = galsim.ImageD(n * step, n * step, scale=PIX / step)
        return galsim.Convolve(p, galsim.Pixel(PIX)).drawImage(image=im, method="no_pixel",
                                                                offset=(dx * step, dy * step)).array

    N = a.n_stars
    ccd = rng.integers(0, 2, N)
    x, y = rng.uniform(0, 2048, N), rng.uniform(0, 4096, N)
    u, v = (x + 2048 * ccd) / 2048 - 1, y / 2048 - 1
    delta = rng.uniform(-0.5, 0.5, (N, 2))
    snr = 10 ** rng.uniform(np.log10(a.snr_min), 3, N)
    imgs = []
    for i in range(N):
        clean = draw(psf_at(ccd[i], u[i], v[i]), *delta[i])
        imgs.append(snr[i] * np.sqrt(np.sum(clean ** 2)) / np.sum(clean ** 2) * clean + rng.normal(0, 1, clean.shape))
    true_off = np.stack([0.2 - 0.3 * ccd + 0.25 * (x / 2048 - 0.5) - 0.1 * (y / 4096 - 0.5),
                         -0.1 + 0.2 * ccd + 0.15 * (y / 4096 - 0.5)], axis=1)
    st = StarSet(image=np.array(imgs), ivar=np.ones((N, n, n)), delta=delta - true_off, ccd=ccd, u=u, v=v, x=x,
                 y=y, snr=snr)
    t0 = time.perf_counter()
    model, used, info = fit_pixel_psf(st, 2, order=a.order, oversampling=k, ccd_shape=[(4096, 2048)] * 2,
                                      alias_width=a.alias_width, native_width=a.native_width,
                                      iterations=a.iterations)
    print(f"{N} stars (SNR {a.snr_min:.0f}-1000), FWHM {a.fwhm}\" ({a.fwhm / PIX:.1f} pixels), order {a.order}, "
          f"oversampling {k}, {a.iterations} iterations: fitted in {time.perf_counter() - t0:.1f} s, {len(used)} stars kept")
    res, de, rings = [], [], []
    # rings of |k| (radians per native pixel) for the transform's error; Nyquist is pi
    edges = np.array([0.0, 1.0, 2.0, 2.5, np.pi, k * np.pi * np.sqrt(2) + 1e-9])
    kf = 2 * np.pi * np.fft.fftfreq(n * k) * k
    kk = np.hypot(kf[:, None], kf[None, :])
    for _ in range(50):
        c = int(rng.integers(0, 2))
        uu = rng.uniform(-1, 0) if c == 0 else rng.uniform(0, 1)
        vv = rng.uniform(-1, 1)
        m = model.image(c, uu, vv)
        t = draw(psf_at(c, uu, vv), 0, 0, step=k)
        t /= t.sum()
        # per native pixel: a fine pixel holds 1/k^2 of a native pixel's flux
        res.append(np.sqrt(np.mean((m - t) ** 2)) * k * k)
        dP = np.abs(np.fft.fft2(np.fft.ifftshift(m - t)))
        rings.append([np.sqrt(np.mean(dP[(kk >= lo) & (kk < hi)] ** 2)) for lo, hi in zip(edges[:-1], edges[1:])])
        mm, mt = galsim.hsm.FindAdaptiveMom(galsim.Image(m)), galsim.hsm.FindAdaptiveMom(galsim.Image(t))
        de.append((mm.observed_shape.e1 - mt.observed_shape.e1, mm.observed_shape.e2 - mt.observed_shape.e2,
                   mm.moments_sigma / mt.moments_sigma - 1, mt.observed_shape.e1, mt.observed_shape.e2))
    de = np.array(de)
    # a model rounder (or more elliptical) than the truth shows as a slope of the residual against e
    et = np.concatenate([de[:, 3], de[:, 4]])
    slope = float(np.polyfit(et, np.concatenate([de[:, 0], de[:, 1]]), 1)[0])
    reg = np.array([model.registration_shift(c, xx, yy) for c, xx, yy in zip(ccd, x, y)])
    print(f"  model - true PSF, rms per pixel / flux: mean {np.mean(res):.2e}, max {np.max(res):.2e}")
    print(f"  ellipticity residual: rms e1 {np.sqrt(np.mean(de[:, 0] ** 2)):.2e}, e2 {np.sqrt(np.mean(de[:, 1] ** 2)):.2e}"
          f" (mean {de[:, 0].mean():+.1e}, {de[:, 1].mean():+.1e}); size (sigma) residual rms "
          f"{np.sqrt(np.mean(de[:, 2] ** 2)):.2e} (mean {de[:, 2].mean():+.1e}); d e / e {slope:+.3f}")
    labels = [f"{lo:.1f}-{hi:.1f}" for lo, hi in zip(edges[:-1], edges[1:])]
    labels[-1] = f"{edges[-2]:.1f}-"
    print("  transform error |P_model - P_true| (P(0) = 1), rms per ring of |k| (rad/pixel): "
          + ", ".join(f"{lab} {v:.1e}" for lab, v in zip(labels, np.sqrt(np.mean(np.array(rings) ** 2, axis=0)))))
    print(f"  registration error at the stars: rms {np.sqrt(np.mean((reg - true_off) ** 2)):.4f} pixel, "
          f"max {np.abs(reg - true_off).max():.4f} pixel")


if __name__ == "__main__":
    main()
