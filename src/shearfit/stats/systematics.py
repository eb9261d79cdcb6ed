"""Systematics tests of a shear catalogue (sec. 7 and 8): ``shearfit systematics``.

- The PSF-galaxy cross-correlation, the weighted mean of e . e_psf, in bins
  of SNR and of fitted scalelength, with errors from 10 random subsamples
  (rms of the subsample values / sqrt(10), as the paper), per catalogue
  (field) and for all together. Noise bias correlates galaxies with the PSF
  at low SNR (App. C); above SNR ~20 it should vanish.
- The distribution of the weights against magnitude, scalelength and SNR.
- With the truth table of a simulation: the weight bias, the weighted mean
  intrinsic ellipticity <w e_int> / <w> against PSF ellipticity (both
  components together) in four groups of size x SNR.
"""

from __future__ import annotations

import os

import numpy as np
from astropy.table import Table, join, vstack

from ..errors import ShearfitIOError, ShearfitValueError

__all__ = ["read_catalogs", "equal_number_edges", "psf_galaxy_xcorr", "weight_distribution", "weight_bias", "run_systematics"]

_NEEDED = ("id", "e1", "e2", "psf_e1", "psf_e2", "weight", "fitclass", "snr", "scalelength", "mag")


def read_catalogs(paths, truth=None):
    """The measured galaxies (fitclass 0, weight > 0) of each catalogue, labelled, with truth columns if given."""
    out = []
    truth_tab = None
    if truth is not None:
        try:
            truth_tab = Table.read(truth)
        except (OSError, ValueError) as exc:
            raise ShearfitIOError(f"{truth}: cannot read the truth table: {str(exc).splitlines()[0]}") from None
        for col in ("id", "e1_int", "e2_int"):
            if col not in truth_tab.colnames:
                raise ShearfitIOError(f"{truth}: truth table has no column {col!r}")
        truth_tab = truth_tab[["id", "e1_int", "e2_int"] + (["is_star"] if "is_star" in truth_tab.colnames else [])]
    for k, p in enumerate(paths):
        try:
            t = Table.read(p)
        except (OSError, ValueError) as exc:
            raise ShearfitIOError(f"{p}: cannot read the shear catalogue: {str(exc).splitlines()[0]}") from None
        for col in _NEEDED:
            if col not in t.colnames:
                raise ShearfitIOError(f"{p}: shear catalogue has no column {col!r}")
        keep = (np.asarray(t["fitclass"]) == 0) & (np.asarray(t["weight"], float) > 0)
        for col in ("e1", "e2", "psf_e1", "psf_e2", "snr", "scalelength"):
            keep &= np.isfinite(np.asarray(t[col], float))
        t = t[keep][list(_NEEDED)]
        if truth_tab is not None:
            t = join(t, truth_tab, keys="id")
            if "is_star" in t.colnames:
                t = t[~np.asarray(t["is_star"], bool)]
        t["field"] = k
        out.append(t)
    if not any(len(t) for t in out):
        raise ShearfitValueError("no measured galaxy (fitclass 0, weight > 0) in " + ", ".join(map(str, paths)))
    return out


def _subsample_mean(values, weights, n_sub, rng):
    """Weighted mean and its error: rms of the means of ``n_sub`` random subsamples over sqrt(n_sub)."""
    if values.size == 0 or np.sum(weights) <= 0:
        return np.nan, np.nan
    mean = float(np.sum(weights * values) / np.sum(weights))
    if values.size < 2 * n_sub:
        return mean, np.nan
    lab = rng.permutation(values.size) % n_sub
    subs = np.array([np.sum(weights[lab == k] * values[lab == k]) / max(np.sum(weights[lab == k]), 1e-300)
                     for k in range(n_sub)])
    return mean, float(np.sqrt(np.mean((subs - subs.mean()) ** 2)) / np.sqrt(n_sub))


def equal_number_edges(values, n):
    """Bin edges with equal numbers (at least one object per bin)."""
    q = np.quantile(values, np.linspace(0, 1, n + 1))
    q[-1] = np.nextafter(q[-1], np.inf)
    return np.unique(q)


def psf_galaxy_xcorr(tab: Table, column, edges, n_sub=10, rng=None) -> Table:
    """<e . e_psf> (weighted) per bin of ``column``, error from ``n_sub`` random subsamples."""
    rng = rng or np.random.default_rng(0)
    x = np.asarray(tab[column], float)
    w = np.asarray(tab["weight"], float)
    prod = (np.asarray(tab["e1"], float) * np.asarray(tab["psf_e1"], float)
            + np.asarray(tab["e2"], float) * np.asarray(tab["psf_e2"], float))
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        s = (x >= lo) & (x < hi)
        mean, err = _subsample_mean(prod[s], w[s], n_sub, rng)
        xm = float(np.sum(w[s] * x[s]) / np.sum(w[s])) if np.any(s) else np.nan
        rows.append((lo, hi, xm, mean, err, int(s.sum())))
    return Table(rows=rows, names=("lo", "hi", column, "xi_psf_gal", "xi_err", "n"))


def weight_distribution(tab: Table, column, edges) -> Table:
    """Weights per bin of ``column``: mean, median, quartiles, total."""
    x = np.asarray(tab[column], float)
    w = np.asarray(tab["weight"], float)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        s = (x >= lo) & (x < hi)
        q = np.percentile(w[s], [25, 50, 75]) if np.any(s) else [np.nan] * 3
        rows.append((lo, hi, float(np.mean(w[s])) if np.any(s) else np.nan, *q, float(np.sum(w[s])), int(s.sum())))
    return Table(rows=rows, names=("lo", "hi", "mean_weight", "q25", "median", "q75", "sum_weight", "n"))


def weight_bias(tab: Table, n_psf_bins=6, snr_split=None, size_split=None, n_sub=10, rng=None) -> Table:
    """<w e_int>/<w> against PSF ellipticity in four size x SNR groups (both components stacked).

    The groups split at ``snr_split`` and ``size_split`` (default: the medians).
    """
    rng = rng or np.random.default_rng(0)
    snr = np.asarray(tab["snr"], float)
    r = np.asarray(tab["scalelength"], float)
    snr_split = float(np.median(snr)) if snr_split is None else snr_split
    size_split = float(np.median(r)) if size_split is None else size_split
    w = np.asarray(tab["weight"], float)
    ep = np.concatenate([np.asarray(tab["psf_e1"], float), np.asarray(tab["psf_e2"], float)])
    ei = np.concatenate([np.asarray(tab["e1_int"], float), np.asarray(tab["e2_int"], float)])
    ww = np.concatenate([w, w])
    edges = equal_number_edges(ep, n_psf_bins)
    rows = []
    for big in (False, True):
        for bright in (False, True):
            g = np.tile(((r >= size_split) == big) & ((snr >= snr_split) == bright), 2)
            name = f"{'large' if big else 'small'}, {'high' if bright else 'low'} SNR"
            for lo, hi in zip(edges[:-1], edges[1:]):
                s = g & (ep >= lo) & (ep < hi)
                mean, err = _subsample_mean(ei[s], ww[s], n_sub, rng)
                epm = float(np.mean(ep[s])) if np.any(s) else np.nan
                rows.append((name, epm, mean, err, int(s.sum())))
    t = Table(rows=rows, names=("group", "e_psf", "w_e_int", "err", "n"))
    t.meta["SNRSPLIT"] = snr_split
    t.meta["SIZSPLIT"] = size_split
    return t


def run_systematics(paths, out_dir, truth=None, n_bins=8, n_sub=10, seed=0):
    """``shearfit systematics``: tables (systematics.fits) and plots (PNG) in ``out_dir``; returns the tables."""
    from astropy.io import fits

    from ..files import atomic_path

    cats = read_catalogs(paths, truth)
    allc = vstack([c for c in cats if len(c)], metadata_conflicts="silent")   # one SFCONFIG per field
    rng = np.random.default_rng(seed)
    os.makedirs(out_dir, exist_ok=True)
    tables = {}
    for col, key in (("snr", "PSFGAL_SNR"), ("scalelength", "PSFGAL_SIZE")):
        edges = equal_number_edges(np.asarray(allc[col], float), n_bins)
        parts = []
        for label, c in [("all", allc)] + ([(str(p), c) for p, c in zip(paths, cats)] if len(cats) > 1 else []):
            t = psf_galaxy_xcorr(c, col, edges, n_sub, rng)
            t["field"] = label
            parts.append(t)
        tables[key] = vstack(parts)
    for col in ("mag", "scalelength", "snr"):
        tables[f"WEIGHT_{col.upper()[:4]}"] = weight_distribution(allc, col, equal_number_edges(np.asarray(allc[col], float),
                                                                                     n_bins))
    if truth is not None:
        tables["WEIGHTBIAS"] = weight_bias(allc, n_sub=n_sub, rng=rng)
    hdus = [fits.PrimaryHDU()]
    for name, t in tables.items():
        h = fits.table_to_hdu(t)
        h.name = name
        hdus.append(h)
    hdus[0].header["NGAL"] = (len(allc), "measured galaxies used")
    with atomic_path(os.path.join(out_dir, "systematics.fits")) as tmp:
        fits.HDUList(hdus).writeto(tmp)
    _plots(out_dir, tables, allc)
    return tables


def _plots(out_dir, tables, allc):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..files import atomic_path

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for a, key, col, log in ((ax[0], "PSFGAL_SNR", "snr", True), (ax[1], "PSFGAL_SIZE", "scalelength", False)):
        t = tables[key]
        for label in dict.fromkeys(t["field"]):
            s = t["field"] == label
            a.errorbar(t[col][s], t["xi_psf_gal"][s], t["xi_err"][s], fmt="o-" if label == "all" else ".",
                       ms=4, lw=1 if label == "all" else 0.5, label=label if label == "all" else None)
        a.axhline(0, color="k", lw=0.5)
        a.set_xlabel("SNR" if col == "snr" else "scalelength (arcsec)")
        a.set_ylabel("<e . e_psf> (weighted)")
        if log:
            a.set_xscale("log")
    ax[0].legend(fontsize=8)
    fig.suptitle("PSF-galaxy cross-correlation (errors: 10 random subsamples)", fontsize=10)
    with atomic_path(os.path.join(out_dir, "psf_galaxy.png")) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)

    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    w = np.asarray(allc["weight"], float)
    for a, col, log in ((ax[0], "mag", False), (ax[1], "scalelength", False), (ax[2], "snr", True)):
        x = np.asarray(allc[col], float)
        xb = np.geomspace(max(x.min(), 1e-3), x.max(), 40) if log else np.linspace(x.min(), x.max(), 40)
        a.hist2d(x, w, bins=[xb, 40], cmap="Greys", cmin=1)
        t = tables[f"WEIGHT_{col.upper()[:4]}"]
        a.plot(0.5 * (t["lo"] + t["hi"]), t["mean_weight"], "r.-", label="mean weight")
        a.set_xlabel(col)
        a.set_ylabel("weight")
        if log:
            a.set_xscale("log")
    ax[0].legend(fontsize=8)
    with atomic_path(os.path.join(out_dir, "weights.png")) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)

    if "WEIGHTBIAS" in tables:
        t = tables["WEIGHTBIAS"]
        fig, a = plt.subplots(figsize=(6, 4.5))
        for g in dict.fromkeys(t["group"]):
            s = t["group"] == g
            a.errorbar(t["e_psf"][s], t["w_e_int"][s], t["err"][s], fmt="o-", ms=3, label=g)
        a.axhline(0, color="k", lw=0.5)
        a.set_xlabel("PSF ellipticity (component)")
        a.set_ylabel("<w e_int> / <w> (same component)")
        a.legend(fontsize=8)
        with atomic_path(os.path.join(out_dir, "weight_bias.png")) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
