#!/usr/bin/env python
"""How well a native-sampled PSF is carried above Nyquist: shearfit's model against GalSim's rendering.

For Moffat PSFs from well sampled to narrower than two pixels (0.187 arcsec
pixels), round and elliptical, a small galaxy (exponential disk + bulge,
scalelength 0.15 arcsec, e = (0.3, 0.5)) is rendered by GalSim and by
shearfit (``render_object``) from a PSF image at the stamp's sampling, with
the App. A correction off ('none': the band-limited assumption), on with the
Moffat fitted to the PSF image ('moffat', the engine's default), and on with
the PSF's true Moffat size and beta ('true Moffat': what a perfect fit would
give); an oversampled PSF image (3x, no correction) shows the exact fold.
Prints the largest difference over the stamp in units of the peak (the
model tests ask for 1e-3).

    python benchmarks/alias_correction.py
"""

from __future__ import annotations

import numpy as np

import shearfit
from shearfit.engine.model import psf_moffat
from shearfit.simulate.stamps import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf

PIX = 0.187
J = PIX * np.eye(2)
GAL = dict(r=0.15, e1=0.3, e2=0.5, B=0.2, offset=(0.12, 0.43))


def model_error(psf, alias="moffat", os=1, moffat=None, n=48):
    gal = galaxy_profile(GAL["r"], GAL["B"], GAL["e1"], GAL["e2"], flux=1.0)
    ref = draw_stamp(gal, psf, J, offset=GAL["offset"], stamp_size=n)
    pim = draw_psf_image(psf, J, size=2 * n * os, oversampling=os)
    obs = shearfit.Observation(image=ref, weight=np.ones_like(ref), psf=pim, psf_oversampling=os, jacobian=J,
                               offset=GAL["offset"], psf_moffat=moffat)
    mod = shearfit.render_object(obs, GAL["e1"], GAL["e2"], GAL["r"], GAL["B"], 1.0,
                                 config={"alias_correction": alias})
    return np.abs(mod - ref).max() / ref.max()


def main():
    print("largest |shearfit - GalSim| over the stamp, in units of its peak "
          f"(disk+bulge r = {GAL['r']}\", e = ({GAL['e1']}, {GAL['e2']}), {PIX}\" pixels)\n")
    print(f"{'FWHM':>6s} {'pix':>5s} {'beta':>5s} {'e_psf':>12s} | {'none':>8s} {'moffat':>8s} {'true Moffat':>11s} "
          f"{'3x PSF':>8s} | fitted (rs, beta) / true")
    for fwhm in (0.6, 0.45, 0.38, 0.32, 0.25):
        for beta in (2.5, 4.5):
            rs_true = fwhm / PIX / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
            for e in ((0.0, 0.0), (0.08, 0.02)):
                psf = moffat_psf(fwhm, beta, *e)
                fitted = psf_moffat(draw_psf_image(psf, J, size=96, oversampling=1))
                row = [model_error(psf, "none"), model_error(psf, "moffat"),
                       model_error(psf, "moffat", moffat=(rs_true, beta)), model_error(psf, "none", os=3)]
                print(f"{fwhm:6.2f} {fwhm / PIX:5.2f} {beta:5.1f} {str(e):>12s} | "
                      + " ".join(f"{v:8.1e}" if i != 2 else f"{v:11.1e}" for i, v in enumerate(row))
                      + f" | ({fitted[0]:.3f}, {fitted[1]:.2f}) / ({rs_true:.3f}, {beta})")


if __name__ == "__main__":
    main()
