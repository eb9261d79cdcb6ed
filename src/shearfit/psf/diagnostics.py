"""Diagnostics of a fitted PSF model (sec. 5), as FITS and PNG files a person looks at.

Per exposure: the model at each CCD's centre; the mean residual (star minus
model, flux-normalised) per CCD; the bootstrap rms of that mean residual
(the paper's 64 resamplings of the stars, each a full refit); and, on a
grid over the field, the model's ellipticity (a whisker plot) and the
fraction of its light in the central pixel.
"""

from __future__ import annotations


import numpy as np
from astropy.io import fits

from ..files import atomic_path
from ..io.wcs import pixel_to_sky
from .build import FieldFrame
from .pixelmodel import fit_pixel_psf, residual_images

__all__ = ["psf_diagnostics", "write_diagnostics", "model_moments"]


def model_moments(img, step=1.0):
    """(e1, e2, sigma in pixels) of an image from GalSim's adaptive moments; NaN if they fail."""
    import galsim

    try:
        m = galsim.hsm.FindAdaptiveMom(galsim.Image(np.ascontiguousarray(img), scale=1.0))
    except galsim.errors.GalSimHSMError:
        return np.nan, np.nan, np.nan
    return m.observed_shape.e1, m.observed_shape.e2, m.moments_sigma * step


def psf_diagnostics(result, ccds, n_bootstrap=64, grid=8, seed=0, pc=None):
    """Numbers and images describing one exposure's model (see module doc)."""
    model, stars = result.model, result.stars
    frame = FieldFrame(**model.frame)
    k = model.oversampling
    out = {"centre_images": [], "mean_residual": [], "boot_rms": [], "n_stars": []}
    res, _ = residual_images(model, stars)
    for c, ccd in enumerate(ccds):
        ny, nx = ccd.shape
        if model.ccd_used[c]:
            ra, dec = pixel_to_sky(ccd.wcs, (nx - 1) / 2, (ny - 1) / 2)
            u, v = frame.uv(ra, dec)
            out["centre_images"].append(model.image(c, float(u), float(v)))
        else:
            out["centre_images"].append(np.zeros((k * model.size,) * 2))
        sel = stars.ccd == c
        out["n_stars"].append(int(sel.sum()))
        out["mean_residual"].append(res[sel].mean(axis=0) if sel.any() else np.zeros(res.shape[1:]))
    # bootstrap: refit on resampled stars (centring kept), mean residual of the original stars per CCD
    rng = np.random.default_rng(seed)
    boots = []
    for _ in range(int(n_bootstrap)):
        idx = rng.integers(0, len(stars), len(stars))
        try:
            mb, _, _ = fit_pixel_psf(stars.subset(idx), model.n_ccd, order=model.order, oversampling=k,
                                     alias_order=model.alias_order, iterations=0, centre=False, clip=0,
                                     native_width=1.0 if pc is None else pc.psf_native_width)
        except Exception:   # a resampling without enough stars on a CCD
            continue
        if not np.array_equal(mb.ccd_used, model.ccd_used):
            continue
        rb, _ = residual_images(mb, stars)
        boots.append(np.array([rb[stars.ccd == c].mean(axis=0) if np.any(stars.ccd == c)
                               else np.zeros(rb.shape[1:]) for c in range(len(ccds))]))
    if boots:
        b = np.array(boots)
        out["boot_rms"] = list(np.sqrt(np.mean((b - b.mean(axis=0)) ** 2, axis=0)))
    else:
        out["boot_rms"] = [np.zeros(res.shape[1:]) for _ in ccds]
    out["n_boot"] = len(boots)
    # ellipticity and central-pixel fraction over a grid on each CCD
    rows = []
    for c, ccd in enumerate(ccds):
        if not model.ccd_used[c]:
            continue
        ny, nx = ccd.shape
        for gy in (np.arange(grid) + 0.5) * ny / grid:
            for gx in (np.arange(grid) + 0.5) * nx / grid:
                ra, dec = pixel_to_sky(ccd.wcs, gx, gy)
                u, v = frame.uv(ra, dec)
                img = model.image(c, float(u), float(v))
                e1, e2, sig = model_moments(img, 1.0 / k)
                native = img.reshape(model.size, k, model.size, k).sum(axis=(1, 3)) if k > 1 else img
                rows.append((c, gx, gy, float(u), float(v), e1, e2, sig, float(native.max())))
    out["grid"] = np.array(rows, dtype=[("ccd", "i4"), ("x", "f8"), ("y", "f8"), ("u", "f8"), ("v", "f8"),
                                        ("e1", "f8"), ("e2", "f8"), ("sigma", "f8"), ("central_fraction", "f8")])
    return out


def write_diagnostics(diag, result, path_prefix):
    """``PREFIX.psfdiag.fits`` and ``PREFIX.psf_whisker.png``, ``PREFIX.psf_central.png``; returns the paths."""
    hdus = [fits.PrimaryHDU()]
    hdus[0].header["NBOOT"] = (diag["n_boot"], "bootstrap resamplings used")
    hdus.append(fits.ImageHDU(np.array(diag["centre_images"]), name="MODEL_AT_CCD_CENTRES"))
    hdus.append(fits.ImageHDU(np.array(diag["mean_residual"]), name="MEAN_RESIDUAL"))
    hdus.append(fits.ImageHDU(np.array(diag["boot_rms"]), name="BOOTSTRAP_RMS"))
    hdus.append(fits.BinTableHDU(diag["grid"], name="GRID"))
    st = result.stars
    hdus.append(fits.BinTableHDU.from_columns([
        fits.Column("ccd", "J", array=st.ccd), fits.Column("x", "D", array=st.x), fits.Column("y", "D", array=st.y),
        fits.Column("snr", "D", array=st.snr), fits.Column("dx", "D", array=result.info["offset"][:, 0]),
        fits.Column("dy", "D", array=result.info["offset"][:, 1]),
        fits.Column("chi2", "D", array=result.info["chi2"])], name="STARS"))
    fits_path = f"{path_prefix}.psfdiag.fits"
    with atomic_path(fits_path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True)
    paths = [fits_path]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = diag["grid"]
    e = np.hypot(g["e1"], g["e2"])
    ang = 0.5 * np.arctan2(g["e2"], g["e1"])
    fig, ax = plt.subplots(figsize=(6, 6))
    scale = 0.1 / max(np.nanmax(e), 1e-6)
    ax.quiver(g["u"], g["v"], e * np.cos(ang), e * np.sin(ang), headwidth=0, headlength=0, headaxislength=0,
              pivot="middle", angles="xy", scale_units="xy", scale=1 / scale)
    ax.set_xlabel("u (field, west)")
    ax.set_ylabel("v (field, north)")
    ax.set_title(f"PSF ellipticity (pixel frame), max {np.nanmax(e):.3f}")
    ax.set_aspect("equal")
    p = f"{path_prefix}.psf_whisker.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    fig, ax = plt.subplots(figsize=(6, 5))
    sc = ax.scatter(g["u"], g["v"], c=g["central_fraction"], s=60, marker="s", cmap="gray_r")
    fig.colorbar(sc, label="fraction of light in the central pixel")
    ax.set_aspect("equal")
    p = f"{path_prefix}.psf_central.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    return paths
