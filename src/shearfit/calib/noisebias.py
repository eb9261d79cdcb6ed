"""Appendix C: bias of the mean-likelihood ellipticity for a Gaussian galaxy and a Gaussian PSF.

A Gaussian galaxy of ellipticity e and size s has the surface-brightness
covariance (App. C; e = (a - b)/(a + b))::

    C(e, s) = s^2 / (1 - e^2)^2 [[1 + 2 e1 + e^2, 2 e2], [2 e2, 1 - 2 e1 + e^2]]

and convolving with a Gaussian PSF adds the covariances. With the model's
amplitude marginalised, the expected log-likelihood of a model M for data
made of galaxy G, PSF P and stationary noise at profile-weighted SNR nu is,
up to an additive constant, eq. (C mess)::

    <log L>(M) = 2 nu^2 |C_G + C_P|^(1/2) |C_M + C_P|^(1/2) / |C_G + 2 C_P + C_M|

(its maximum, nu^2 / 2, is at M = G). The likelihood mean over model
ellipticities, with the model's size held at the galaxy's as in the paper, is
biased towards e = 0 and towards the PSF; :func:`population_bias` turns that
into the shear bias 1 + m and the PSF-galaxy cross-correlation of the
paper's population example, and :func:`monte_carlo` checks the expectation
against noisy Gaussian images rendered by GalSim.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["gaussian_cov", "expected_loglike", "ellipticity_grid", "likelihood_mean", "population_bias",
           "monte_carlo_bias", "contour_surface", "run_noisebias", "NoiseBiasCurve"]


def gaussian_cov(e1, e2, s):
    """Covariance matrices (..., 2, 2) of Gaussians of ellipticity (e1, e2) and size s."""
    e1, e2, s = np.broadcast_arrays(np.asarray(e1, float), np.asarray(e2, float), np.asarray(s, float))
    esq = e1 * e1 + e2 * e2
    f = s * s / (1 - esq) ** 2
    out = np.empty(e1.shape + (2, 2))
    out[..., 0, 0] = f * (1 + 2 * e1 + esq)
    out[..., 1, 1] = f * (1 - 2 * e1 + esq)
    out[..., 0, 1] = out[..., 1, 0] = f * 2 * e2
    return out


def _det(c):
    return c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0]


def expected_loglike(model_e1, model_e2, model_size, gal_e, gal_size, psf_e, psf_size, snr):
    """<log L> of models (e1, e2, size) for a Gaussian galaxy and PSF at SNR nu (eq. C mess)."""
    cg = gaussian_cov(gal_e[0], gal_e[1], gal_size)
    cp = gaussian_cov(psf_e[0], psf_e[1], psf_size)
    cm = gaussian_cov(model_e1, model_e2, model_size)
    return 2 * snr ** 2 * np.sqrt(_det(cg + cp) * _det(cm + cp)) / _det(cg + 2 * cp + cm)


def ellipticity_grid(step=0.01, e_max=0.98):
    """Model ellipticities on a square lattice inside |e| < e_max (each sample stands for step^2)."""
    n = int(np.floor(e_max / step))
    ax = np.arange(-n, n + 1) * step
    E1, E2 = np.meshgrid(ax, ax, indexing="ij")
    keep = E1 ** 2 + E2 ** 2 < e_max ** 2
    return E1[keep], E2[keep]


def likelihood_mean(loglike, e1, e2):
    """Likelihood-weighted mean ellipticity (sec. 3.4, no prior) of log-likelihoods on a uniform grid."""
    w = np.exp(loglike - np.max(loglike, axis=-1, keepdims=True))
    norm = np.sum(w, axis=-1)
    return np.sum(w * e1, axis=-1) / norm, np.sum(w * e2, axis=-1) / norm


def _refined_mean(fun, e1, e2, step, e_max, depth=40.0, n_fine=161):
    """Likelihood mean of ``fun(e1, e2)`` (log L) on the grid, or on a finer one where it is too narrow for it.

    Where the region with log L above its maximum minus ``depth`` spans fewer
    than 40 grid steps, the integral is taken again over that region's
    bounding box (plus two steps) on an ``n_fine`` x ``n_fine`` grid.
    """
    ll = fun(e1, e2)
    hot = ll > ll.max() - depth
    lo1, hi1 = e1[hot].min() - 2 * step, e1[hot].max() + 2 * step
    lo2, hi2 = e2[hot].min() - 2 * step, e2[hot].max() + 2 * step
    if max(hi1 - lo1, hi2 - lo2) >= 40 * step:
        return likelihood_mean(ll, e1, e2)
    a, b = np.meshgrid(np.linspace(lo1, hi1, n_fine), np.linspace(lo2, hi2, n_fine), indexing="ij")
    keep = a ** 2 + b ** 2 < e_max ** 2
    a, b = a[keep], b[keep]
    return likelihood_mean(fun(a, b), a, b)


def _compose(e_int, g):
    """Ellipticity (a-b)/(a+b) of an object of intrinsic ellipticity e_int sheared by reduced shear g."""
    # e as a complex number transforms like a reduced shear: e = (e_int + g) / (1 + g* e_int)
    e_int = np.asarray(e_int, complex)
    g = complex(*g)
    return (e_int + g) / (1 + np.conj(g) * e_int)


@dataclass
class NoiseBiasCurve:
    """The paper's appendix C population example at each SNR."""

    snr: np.ndarray
    one_plus_m: np.ndarray      # <e_1> / g_1 with the shear on
    c2: np.ndarray              # <e_2> with the shear on (the PSF is along e2)
    xi_psf_gal: np.ndarray      # <e . e_psf> without shear


def population_bias(snr, e_int=0.25, shear=(0.05, 0.0), psf_e=(0.0, 0.1), size=3.0, psf_size=3.0,
                    n_angles=32, step=0.01, e_max=0.98, refine=True) -> NoiseBiasCurve:
    """1 + m and the PSF-galaxy cross-correlation from the expected likelihood surfaces (App. C, Fig. C2).

    Galaxies of intrinsic ellipticity ``e_int`` at ``n_angles`` orientations
    (uniform, so that the intrinsic ellipticity averages out exactly), sheared
    by ``shear``, PSF of ellipticity ``psf_e``; galaxy, model and PSF of one
    size. 1 + m = <e_1>/g_1; xi = <e . e_psf> for the same galaxies unsheared.
    With ``refine``, a surface narrower than the grid resolves (high SNR) is
    integrated again on a finer grid over the region within 40 of its
    maximum in log L (see ``_refined_mean``); without, on the grid as it is
    (the Monte Carlo comparison uses the same grid for both).
    """
    snr = np.atleast_1d(np.asarray(snr, float))
    e1, e2 = ellipticity_grid(step, e_max)
    phi = np.pi * (np.arange(n_angles) + 0.5) / n_angles
    e_in = e_int * np.exp(2j * phi)
    out = {k: [] for k in ("m", "c2", "xi")}
    for nu in snr:
        means = {}
        for key, g in (("shear", shear), ("none", (0.0, 0.0))):
            eg = _compose(e_in, g)
            if refine:
                ms = [_refined_mean(lambda a, b, e=e: expected_loglike(a, b, size, (e.real, e.imag), size, psf_e,
                                                                       psf_size, nu), e1, e2, step, e_max)
                      for e in eg]
                means[key] = tuple(np.array(v) for v in zip(*ms))
                continue
            ll = np.stack([expected_loglike(e1, e2, size, (e.real, e.imag), size, psf_e, psf_size, nu) for e in eg])
            means[key] = likelihood_mean(ll, e1, e2)
        m1, m2 = means["shear"]
        out["m"].append(np.mean(m1) / shear[0] if shear[0] else np.nan)
        out["c2"].append(np.mean(m2))
        n1, n2 = means["none"]
        out["xi"].append(np.mean(n1 * psf_e[0] + n2 * psf_e[1]))
    return NoiseBiasCurve(snr=snr, one_plus_m=np.array(out["m"]), c2=np.array(out["c2"]),
                          xi_psf_gal=np.array(out["xi"]))


def _model_images(e1, e2, size, psf_e, psf_size, n):
    """Unit-peak Gaussian model images (galaxy convolved with the PSF) sampled at pixel centres."""
    c = np.arange(n) - (n - 1) / 2.0
    X, Y = np.meshgrid(c, c, indexing="xy")
    cov = gaussian_cov(e1, e2, size) + gaussian_cov(psf_e[0], psf_e[1], psf_size)
    inv = np.linalg.inv(cov)
    q = (inv[:, 0, 0, None] * X.ravel() ** 2 + 2 * inv[:, 0, 1, None] * X.ravel() * Y.ravel()
         + inv[:, 1, 1, None] * Y.ravel() ** 2)
    return np.exp(-0.5 * q)


def _galsim_gaussian(galsim, e, s):
    """GalSim's Gaussian with the covariance C(e, s) of App. C.

    GalSim's shear keeps the area; C(e, s) has semi-axes s/(1-e) and s/(1+e),
    an area larger by 1/(1-e^2): the sigma before the shear is s/sqrt(1-e^2).
    """
    esq = e[0] ** 2 + e[1] ** 2
    return galsim.Gaussian(sigma=s / np.sqrt(1 - esq)).shear(g1=e[0], g2=e[1])


def _surfaces(clean, sigma, models, mm, n_pairs, rng, chunk=64):
    """Log-likelihood surfaces of noisy realisations, in antithetic pairs (noise n and -n).

    Returns the (2 n_pairs, n_e) surfaces, each pair in adjacent rows.
    """
    d0 = models @ clean.ravel()
    out = []
    for start in range(0, n_pairs, chunk):
        k = min(chunk, n_pairs - start)
        noise = rng.normal(0.0, sigma, (clean.size, k))
        dn = models @ noise
        lp = (d0[:, None] + dn) ** 2 / (2 * sigma ** 2 * mm[:, None])
        lm = (d0[:, None] - dn) ** 2 / (2 * sigma ** 2 * mm[:, None])
        out.append(np.stack([lp.T, lm.T], axis=1).reshape(2 * k, -1))
    return np.concatenate(out)   # (2 n_pairs, n_e): the realisations +n and -n of a pair in adjacent rows


def monte_carlo_bias(snr, e_int=0.25, shear=(0.05, 0.0), psf_e=(0.0, 0.1), size=3.0, psf_size=3.0,
                     n_angles=8, n_pairs=200, step=0.02, e_max=0.6, stamp=96, n_groups=10, seed=0):
    """The population example of :func:`population_bias` from noisy Gaussian images rendered by GalSim.

    For each orientation, ``n_pairs`` antithetic pairs of noise realisations
    (noise n and -n: the term linear in the noise cancels in their mean, so
    the mean log-likelihood converges fast) are added to GalSim's rendering
    of the Gaussian galaxy convolved with the Gaussian PSF (sampled at pixel
    centres, as the formula's sums); each realisation's amplitude-marginalised
    log-likelihood ``[sum f_M f]^2 / (2 sigma^2 sum f_M^2)`` is computed on
    the model grid (sizes held at the truth). The expectation <log L> is
    their mean, and 1 + m and xi follow as in :func:`population_bias`, on the
    same grid (|e| < ``e_max``; the stamp holds the widest model to 6 sigma).
    Errors: jackknife over ``n_groups`` groups of realisations.

    Also returned: the same statistics from each realisation's own likelihood
    mean, averaged (what an estimator applied to each image gives), which is
    not what the expected surface describes.
    """
    import galsim

    snr = np.atleast_1d(np.asarray(snr, float))
    rng = np.random.default_rng(seed)
    e1, e2 = ellipticity_grid(step, e_max)
    models = _model_images(e1, e2, size, psf_e, psf_size, stamp)
    mm = np.sum(models ** 2, axis=1)
    phi = np.pi * (np.arange(n_angles) + 0.5) / n_angles
    e_in = e_int * np.exp(2j * phi)
    psf = _galsim_gaussian(galsim, psf_e, psf_size)
    res = {k: [] for k in ("m", "m_err", "xi", "xi_err", "m_each", "m_each_err", "xi_each", "xi_each_err",
                           "m_analytic", "xi_analytic")}
    for nu in snr:
        # per case (shear on / off) and orientation: mean surface per jackknife group, realisation means
        jk = {}
        each = {}
        for key, g in (("shear", shear), ("none", (0.0, 0.0))):
            groups, own = [], []
            for e in _compose(e_in, g):
                clean = galsim.Convolve(_galsim_gaussian(galsim, (e.real, e.imag), size), psf).drawImage(
                    nx=stamp, ny=stamp, scale=1.0, method="no_pixel").array
                sigma = np.sqrt(np.sum(clean ** 2)) / nu
                ll = _surfaces(clean, sigma, models, mm, n_pairs, rng)
                # jackknife groups of whole pairs: the linear noise term cancels within each
                pairs = ll.reshape(n_pairs, 2, -1).mean(axis=1)
                groups.append(np.array([g_.mean(axis=0) for g_ in np.array_split(pairs, n_groups)]))
                own.append(np.stack(likelihood_mean(ll, e1, e2), axis=1))   # (2 n_pairs, 2)
            jk[key] = np.stack(groups)            # (n_angles, n_groups, n_e)
            each[key] = np.stack(own)             # (n_angles, 2 n_pairs, 2)

        def stats(surf_shear, surf_none):
            a1, _ = likelihood_mean(surf_shear, e1, e2)
            b1, b2 = likelihood_mean(surf_none, e1, e2)
            return np.mean(a1) / shear[0], np.mean(b1 * psf_e[0] + b2 * psf_e[1])

        full = stats(jk["shear"].mean(axis=1), jk["none"].mean(axis=1))
        leave = np.array([stats(np.delete(jk["shear"], k, axis=1).mean(axis=1),
                                np.delete(jk["none"], k, axis=1).mean(axis=1)) for k in range(n_groups)])
        err = np.sqrt((n_groups - 1) / n_groups * np.sum((leave - leave.mean(axis=0)) ** 2, axis=0))
        res["m"].append(full[0])
        res["xi"].append(full[1])
        res["m_err"].append(err[0])
        res["xi_err"].append(err[1])
        # each realisation's own likelihood mean, averaged over orientations (errors over realisations)
        m_each = each["shear"][:, :, 0].mean(axis=0) / shear[0]
        xi_each = (each["none"][:, :, 0] * psf_e[0] + each["none"][:, :, 1] * psf_e[1]).mean(axis=0)
        res["m_each"].append(m_each.mean())
        res["m_each_err"].append(m_each.std() / np.sqrt(m_each.size))
        res["xi_each"].append(xi_each.mean())
        res["xi_each_err"].append(xi_each.std() / np.sqrt(xi_each.size))
        an = population_bias([nu], e_int, shear, psf_e, size, psf_size, n_angles, step, e_max, refine=False)
        res["m_analytic"].append(an.one_plus_m[0])
        res["xi_analytic"].append(an.xi_psf_gal[0])
    return {"snr": snr, **{k: np.array(v) for k, v in res.items()}}


def contour_surface(gal_e=(0.3, 0.0), psf_e=(0.0, 0.3), size=3.0, psf_size=3.0, snr=20.0, step=0.005, e_max=0.98):
    """<log L> minus its maximum on a square grid of model e (the paper's Fig. C1 example), NaN outside |e| < e_max."""
    n = int(np.floor(e_max / step))
    ax = np.arange(-n, n + 1) * step
    E1, E2 = np.meshgrid(ax, ax, indexing="ij")
    inside = E1 ** 2 + E2 ** 2 < e_max ** 2
    ll = np.full(E1.shape, np.nan)
    ll[inside] = expected_loglike(E1[inside], E2[inside], size, gal_e, size, psf_e, psf_size, snr)
    return ax, ll - np.nanmax(ll)


def run_noisebias(out_dir, snr_mc=(5.0, 8.0, 12.0, 20.0, 40.0), n_pairs=2000, seed=0, stream=None):
    """``shearfit noisebias``: App. C's two figures, their numbers, and the Monte Carlo check.

    Writes ``contours.png`` (Fig. C1), ``bias.png`` (Fig. C2 with the Monte
    Carlo points), ``noisebias.fits`` (HDU CURVE: the analytic curves; HDU
    MONTECARLO: the check) and returns the Monte Carlo dict.
    """
    import os
    import sys

    from astropy.io import fits
    from astropy.table import Table

    from ..files import atomic_path

    stream = stream or sys.stdout
    os.makedirs(out_dir, exist_ok=True)
    snr_curve = np.geomspace(3.0, 200.0, 40)
    paper = population_bias(snr_curve)                              # the paper's |e| < 0.98 grid
    same = population_bias(snr_curve, step=0.02, e_max=0.6, n_angles=8, refine=False)   # the Monte Carlo's
    mc = monte_carlo_bias(snr_mc, n_pairs=n_pairs, seed=seed)
    ax, ll = contour_surface()
    k = np.unravel_index(np.nanargmax(ll), ll.shape)
    w = np.exp(np.nan_to_num(ll, nan=-np.inf))
    E1, E2 = np.meshgrid(ax, ax, indexing="ij")
    mean_e = (float(np.sum(w * E1) / np.sum(w)), float(np.sum(w * E2) / np.sum(w)))
    print(f"Appendix C, Fig. C1 example (galaxy e = (0.3, 0), PSF e = (0, 0.3), sizes 3 pixels, SNR 20): "
          f"maximum of <log L> at ({ax[k[0]]:+.3f}, {ax[k[1]]:+.3f}), likelihood mean "
          f"({mean_e[0]:+.4f}, {mean_e[1]:+.4f})", file=stream)
    print("Fig. C2 example (e_int = 0.25, g = (0.05, 0), PSF e = (0, 0.1), galaxy and PSF sizes 3 pixels):",
          file=stream)
    print("   SNR   1+m (paper grid)  1+m (|e|<0.6)   Monte Carlo        pull    xi analytic   xi Monte Carlo"
          "          pull", file=stream)
    for i, nu in enumerate(mc["snr"]):
        an = population_bias([nu])
        pm = (mc["m"][i] - mc["m_analytic"][i]) / mc["m_err"][i]
        px = (mc["xi"][i] - mc["xi_analytic"][i]) / mc["xi_err"][i]
        print(f"  {nu:5.1f}   {an.one_plus_m[0]:.4f}            {mc['m_analytic'][i]:.4f}        "
              f"{mc['m'][i]:.4f} +/- {mc['m_err'][i]:.4f}  {pm:+5.1f}   {mc['xi_analytic'][i]:+.2e}     "
              f"{mc['xi'][i]:+.2e} +/- {mc['xi_err'][i]:.1e}  {px:+5.1f}", file=stream)
    print("  (each realisation's own likelihood mean, averaged: 1+m = "
          + ", ".join(f"{v:.3f}+/-{e:.3f}" for v, e in zip(mc["m_each"], mc["m_each_err"])) + ")", file=stream)

    curve = Table({"snr": snr_curve, "one_plus_m": paper.one_plus_m, "xi_psf_gal": paper.xi_psf_gal,
                   "c2": paper.c2, "one_plus_m_mcgrid": same.one_plus_m, "xi_psf_gal_mcgrid": same.xi_psf_gal})
    mct = Table({k: v for k, v in mc.items()})
    hdus = fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(curve), fits.table_to_hdu(mct)])
    hdus[1].name, hdus[2].name = "CURVE", "MONTECARLO"
    with atomic_path(os.path.join(out_dir, "noisebias.fits")) as tmp:
        hdus.writeto(tmp)
    _plot(out_dir, ax, ll, snr_curve, paper, same, mc)
    return mc


def _plot(out_dir, ax, ll, snr_curve, paper, same, mc):
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..files import atomic_path

    fig, a = plt.subplots(figsize=(5.5, 5))
    levels = -0.5 * np.arange(20, 0, -1)
    a.contour(ax, ax, ll.T, levels=levels, colors="k", linewidths=0.6, linestyles="solid")
    a.plot([0.3], [0.0], "r+", ms=12, label="galaxy and maximum")
    a.plot([0.0], [0.3], "bx", ms=10, label="PSF")
    a.set_xlabel("model e1")
    a.set_ylabel("model e2")
    a.set_aspect("equal")
    a.set_title("<log L>: contours every 0.5 below the maximum, to -10 (SNR 20)", fontsize=9)
    a.legend(fontsize=8)
    with atomic_path(os.path.join(out_dir, "contours.png")) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6, 7), sharex=True)
    a1.plot(snr_curve, paper.one_plus_m, "k-", label="expected surface, |e| < 0.98 (as the paper)")
    a1.plot(snr_curve, same.one_plus_m, "k:", label="expected surface, |e| < 0.6")
    a1.errorbar(mc["snr"], mc["m"], mc["m_err"], fmt="o", color="C0", label="Monte Carlo <log L>, |e| < 0.6")
    a1.errorbar(mc["snr"] * 1.03, mc["m_each"], mc["m_each_err"], fmt="s", mfc="none", color="C1",
                label="mean of each image's estimate")
    a1.axhline(1, color="0.5", lw=0.5)
    a1.set_ylabel("1 + m")
    a1.legend(fontsize=7)
    a2.plot(snr_curve, paper.xi_psf_gal, "k-")
    a2.plot(snr_curve, same.xi_psf_gal, "k:")
    a2.errorbar(mc["snr"], mc["xi"], mc["xi_err"], fmt="o", color="C0")
    a2.errorbar(mc["snr"] * 1.03, mc["xi_each"], mc["xi_each_err"], fmt="s", mfc="none", color="C1")
    a2.axhline(0, color="0.5", lw=0.5)
    a2.set_ylabel("xi PSF-galaxy <e . e_psf>")
    a2.set_xlabel("SNR")
    a2.set_xscale("log")
    fig.tight_layout()
    with atomic_path(os.path.join(out_dir, "bias.png")) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
