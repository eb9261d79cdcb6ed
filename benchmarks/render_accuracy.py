"""render_object against GalSim: the worst pixel error over sizes, shapes, PSFs, samplings and Jacobians.

Every case draws one galaxy (truncated exponential disk, disk + de Vaucouleurs bulge, or pure bulge; the
shared ``shearfit.simulate.stamps.galaxy_profile``) convolved with a PSF whose pixel response is included
(a Moffat of FWHM 0.65" convolved with the pixel, or the DES PSFEx model of ``shared/data/real`` that GalSim's
``DES_PSFEx`` reads), on 0.187" pixels, under a plain Jacobian and under one rotated by 30 degrees with a 2 %
shear, at a sub-pixel offset. shearfit is handed the PSF as an image, native (with the App. A Moffat above
Nyquist) or 3 times oversampled, and ``render_object`` makes the model; the figure is the largest
``|model - reference|`` over the stamp, in units of the reference's peak.

Two references:

- ``sampled``: the image the detector records, the convolution's value at each pixel centre. It is drawn
  9 times finer than the pixels (GalSim's FFT, which holds every mode up to 9 pi) and every ninth pixel kept,
  so that the sampling folds the modes above the pixels' Nyquist frequency, as real pixels do.
- ``galsim``: GalSim's own drawImage at the pixel scale (method ``no_pixel``). Its FFT holds the modes up to
  the pixels' Nyquist frequency only and drops the rest instead of folding them. For the Moffat that is
  nothing; the PSFEx model, a Lanczos-interpolated image, has 1.4e-3 of its peak at |k| = 2 pi per pixel
  (the interpolant's replicas), which sampling folds onto the low modes (0.2 % of a point source's flux).

Then, for native PSF images, what the samples cannot tell (``ambiguity``): the model's PSF has the true PSF's
samples, and where the two still give a small galaxy different images, no renderer that sees only the samples
can be close to both.

    python benchmarks/render_accuracy.py            # the whole grid (a few minutes)
    python benchmarks/render_accuracy.py --quick    # r = 0.05" and 1", the worst shapes
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
from pathlib import Path

import numpy as np

import galsim
import galsim.des

import shearfit
from shearfit.simulate.stamps import galaxy_profile, moffat_psf

PIX = 0.187
PSFEX = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "decam_00154912_12_psfex.psf"
#: the sampled reference is drawn this many times finer than the pixels
FINE = 9
OFFSET = (0.27, -0.41)


def jacobians():
    th = np.radians(30.0)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    return {"plain": PIX * np.eye(2), "rotated 30 deg, 2 % shear": PIX * np.diag([1.02, 0.98]) @ rot}


def psf_in_pixels(name, J, psfex):
    """The PSF in the image's pixel frame, pixel response included."""
    if name == "PSFEx":
        return psfex.getPSF(galsim.PositionD(1024.0, 2048.0))
    wcs = galsim.JacobianWCS(*J.ravel())
    return galsim.Convolve(wcs.toImage(moffat_psf(0.65, 3.0, 0.06, -0.04)), galsim.Pixel(1.0))


def sampled_reference(prof, n):
    """The convolution's values at the n x n pixel centres (see the module's docstring)."""
    fine = prof.drawImage(nx=n * FINE, ny=n * FINE, scale=1.0 / FINE, method="no_pixel",
                          offset=(OFFSET[0] * FINE, OFFSET[1] * FINE), use_true_center=False,
                          dtype=np.float64).array
    return fine[::FINE, ::FINE] * FINE * FINE


def errors(r, e, bulge, psf_pix, J, oversampling):
    """(error against the sampled reference, against GalSim's drawImage) of one case."""
    B, is_bulge = bulge
    n = 48 if r <= 0.6 else int(2 * 4.5 * r / PIX * 1.1 + 24) // 2 * 2
    wcs = galsim.JacobianWCS(*J.ravel())
    conv = galsim.Convolve(wcs.toImage(galaxy_profile(r, B, e[0], e[1], flux=1.0, is_bulge=is_bulge)), psf_pix)
    refs = (sampled_reference(conv, n),
            conv.drawImage(nx=n, ny=n, scale=1.0, method="no_pixel", offset=OFFSET, use_true_center=False,
                           dtype=np.float64).array)
    # the PSF image handed to shearfit: twice the stamp, drawn through GalSim's Fourier path (as every
    # convolution is), unit sum
    pim = galsim.Convolve(galsim.Gaussian(sigma=1e-4), psf_pix).drawImage(
        nx=2 * n * oversampling, ny=2 * n * oversampling, scale=1.0 / oversampling, method="no_pixel",
        use_true_center=False, dtype=np.float64).array
    pim /= pim.sum()
    obs = shearfit.Observation(image=refs[0], weight=np.ones_like(refs[0]), psf=pim, psf_oversampling=oversampling,
                               jacobian=J, offset=OFFSET)
    mod = shearfit.render_object(obs, e[0], e[1], r, 1.0 if is_bulge else B, 1.0,
                                 config={"alias_correction": "moffat" if oversampling == 1 else "none"})
    return tuple(float(np.abs(mod - ref).max() / ref.max()) for ref in refs)


def native_samples(psf_pix, n):
    """The PSF's values at the centres of an n x n pixel grid (origin at pixel (n // 2, n // 2)), as a star
    records them: drawn FINE times finer and decimated, unit sum."""
    fine = psf_pix.drawImage(nx=n * FINE, ny=n * FINE, scale=1.0 / FINE, method="no_pixel", use_true_center=False,
                             dtype=np.float64).array
    start = (n * FINE // 2) % FINE
    out = fine[start::FINE, start::FINE][:n, :n]
    return out / out.sum()


def ambiguity(psf_pix, J, sizes, shapes, bulges):
    """What a native PSF image cannot tell: the model's own PSF (the samples inside the pixels' Nyquist band,
    the App. A Moffat above it) has the true PSF's samples (checked on a point source, r = 1e-4", at the stamp
    centre), yet the two PSFs give a galaxy different images. Returns (point source against the samples, the
    worst |image with the model's PSF - image with the true PSF| / peak over the galaxies): any renderer that
    sees only the samples is at least half of the latter from one of the two."""
    n = 48
    S = native_samples(psf_pix, 2 * n)
    c = slice(n - n // 2, n + n // 2)
    obs = shearfit.Observation(image=np.zeros((n, n)), weight=np.ones((n, n)), psf=S, jacobian=J)
    point = shearfit.render_object(obs, 0.0, 0.0, 1e-4, 0.0, 1.0, config={"alias_correction": "moffat"})
    consistency = float(np.abs(point - S[c, c]).max() / S[c, c].max())
    worst = 0.0
    wcs = galsim.JacobianWCS(*J.ravel())
    for r, e, (B, is_bulge) in itertools.product(sizes, shapes, bulges):
        conv = galsim.Convolve(wcs.toImage(galaxy_profile(r, B, e[0], e[1], flux=1.0, is_bulge=is_bulge)), psf_pix)
        ref = sampled_reference(conv, n)
        obs = shearfit.Observation(image=ref, weight=np.ones_like(ref), psf=S, jacobian=J, offset=OFFSET)
        mod = shearfit.render_object(obs, e[0], e[1], r, 1.0 if is_bulge else B, 1.0,
                                     config={"alias_correction": "moffat"})
        worst = max(worst, float(np.abs(mod - ref).max() / ref.max()))
    return consistency, worst


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="r = 0.05 and 1 arcsec, two shapes")
    args = ap.parse_args(argv)
    if not PSFEX.exists():
        sys.exit(f"render_accuracy: {PSFEX} not found (the shared real data)")
    psfex = galsim.des.DES_PSFEx(str(PSFEX))
    sizes = (0.05, 1.0) if args.quick else (0.05, 0.1, 0.2, 0.6, 1.5, 3.0)
    shapes = ((0.5, 0.3), (0.1, -0.79)) if args.quick else ((0.0, 0.0), (0.5, 0.3), (-0.8, 0.0), (0.1, -0.79))
    bulges = ((0.0, False), (0.5, False), (1.0, True))
    print(f"shearfit {shearfit.__version__}; render_object against GalSim {galsim.__version__}, worst |model - "
          f"reference| / peak over r = {', '.join(map(str, sizes))} arcsec, e = {shapes}, B = 0, 0.5 and pure bulges\n")
    print("| PSF | PSF image | Jacobian | vs sampled | worst case (r, e, B) | vs GalSim drawImage | worst case |")
    print("|---|---|---|---|---|---|---|")
    for psf_name, os_, (jname, J) in itertools.product(("Moffat", "PSFEx"), (1, 3), jacobians().items()):
        psf_pix = psf_in_pixels(psf_name, J, psfex)
        worst = [(0.0, None), (0.0, None)]
        for r, e, b in itertools.product(sizes, shapes, bulges):
            for i, err in enumerate(errors(r, e, b, psf_pix, J, os_)):
                if err > worst[i][0]:
                    worst[i] = (err, (r, e, b[0]))
        label = "native + App. A Moffat" if os_ == 1 else f"{os_}x oversampled"
        print(f"| {psf_name} | {label} | {jname} | {worst[0][0]:.1e} | {worst[0][1]} | {worst[1][0]:.1e} | "
              f"{worst[1][1]} |", flush=True)
    small = tuple(r for r in sizes if r <= 0.2)
    print(f"\nNative PSF images as a star records them (the PSF's values at the pixel centres), r = "
          f"{', '.join(map(str, small))} arcsec, plain Jacobian: two PSFs with these samples, the true one and the "
          f"model's (samples inside the Nyquist band, App. A Moffat above), and the images they give\n")
    print("| PSF | model's point source vs the samples | images of the two PSFs, worst apart | no renderer of the "
          "samples is closer to both than |")
    print("|---|---|---|---|")
    J = jacobians()["plain"]
    for psf_name in ("Moffat", "PSFEx"):
        consistency, apart = ambiguity(psf_in_pixels(psf_name, J, psfex), J, small, shapes, bulges)
        print(f"| {psf_name} | {consistency:.1e} | {apart:.1e} | {apart / 2:.1e} |", flush=True)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
