"""The noise-bias calibration m(SNR, size) from simulations (sec. 8.4).

Measured galaxies (``fitclass`` 0, weight > 0) are matched by ``id`` to the
simulation's truth, and put in bins of measured SNR and measured size with
equal numbers (SNR quantiles first, then size quantiles within each SNR bin;
20 x 20 by default, fewer when the sample is small). The size is the
scalelength in arcsec (``size="scalelength"``, the paper's) or the resolution,
the scalelength over the PSF's FWHM at the object (``size="resolution"``, the
catalogue's ``psf_fwhm``): a galaxy's bias follows its size relative to the
PSF, and a table in arcsec holds only under the seeing of its simulations.
With ``seeing_bins`` > 1 the galaxies are also split into ranges of
``psf_fwhm`` with a table each, applied in place of the one over all of them
(at equal SNR and resolution a larger PSF still biases somewhat more). In
each bin m is
the response of the lensfit-weighted mean ellipticity to the shear, as a
catalogue's shear estimate sum(w e) / sum(w) responds: from galaxies measured
at +g and -g with the same noise (fields of one seed, below), the weighted
least-squares fit e_k = (1 + m) g_k + a_k with an intercept a_k per seed, in
which a galaxy's intrinsic shape cancels between its +g and -g rows. The
intercepts are those of the fit over the whole table (a bin holds a few
galaxies per seed, whose own intercepts would absorb part of the weights'
response below), so that the whole table's m is the bins' m averaged with
their ``sum(w |g|^2)``: applied to its own galaxies the table closes. What the
cancellation leaves is part of m: lensfit's weight depends on |e|, and a
galaxy sheared along its major axis is weighted differently at +g than at -g
(on shearfit's simulated fields this weight response is +0.016 of m over the
paper's population, +0.034 for galaxies of magnitude 23.7-24.5). c_1 and c_2 come from the residuals
``y_k = e_k - e_s,k``, with ``e_s = (e_int + g) / (1 + g* e_int)`` the true
sheared ellipticity: ``y_k = m g_k + c_k`` plus noise, weighted least
squares; the residuals also give m where no galaxy was measured at opposite
shears (and then miss the weights' response, which e_s removes). Errors come
from bootstrap resampling of the bin's galaxies. The shear must vary between
galaxies (a shear field, or several fields) for m and c to separate.

Several simulated fields calibrate together (``calibrate([(measured, truth),
...])``). Fields made from the same seed share galaxies *and pixel noise*
(``shearfit simulate`` with the seed in the truth header and only the shear
changed, as the demo's +g / -g pair): the copies of one galaxy form a group,
binned by the group's mean measured SNR and size and resampled together by
the bootstrap, so that the noise common to the copies cancels in the
difference that m measures, and the errors know it.

Then the paper's form m(nu, r) = beta / ln(nu) exp(-alpha r nu) (r in
arcsec) is fitted to the bins by chi^2; the likelihood of (alpha, beta) on a
grid is kept in the output for the systematic-error resampling of the
two-point functions.
"""

from __future__ import annotations

import os

import numpy as np
import yaml
from astropy.table import Table, join, vstack
from scipy.optimize import least_squares

from ..files import atomic_path, read_yaml_mapping
from .bias import group_resamples
from ..errors import ShearfitIOError, ShearfitValueError

__all__ = ["CalibrationModel", "as_model", "load_calibration", "binned_table", "matched_galaxies", "stack_matched",
           "sheared_ellipticity", "quantity_bins", "bin_indices", "bin_bias", "fit_alpha_beta", "calibrate",
           "read_calibration", "write_calibration", "model_m", "calibration_m", "calibrated_bias", "plot_calibration",
           "weight_bins", "PAPER_ALPHA", "PAPER_BETA", "DEFAULT_CALIBRATION", "default_calibration",
           "default_calibration_record", "DEFAULT_CALIBRATION_SELFCAL", "SIZE_MEASURES", "size_values"]

PAPER_ALPHA = 0.057
PAPER_BETA = -0.37
MIN_PER_BIN = 50
#: what a binned calibration's size axis measures: the scalelength (arcsec) or the resolution, the scalelength
#: over the PSF's FWHM at the object (catalogue column ``psf_fwhm``)
SIZE_MEASURES = ("scalelength", "resolution")


def size_values(tab, size="scalelength"):
    """The size axis of a calibration per row: ``scalelength``, or ``resolution`` = scalelength / psf_fwhm."""
    if size not in SIZE_MEASURES:
        raise ShearfitValueError(f"calibration size {size!r} is not one of {', '.join(SIZE_MEASURES)}")
    r = np.asarray(tab["scalelength"], float)
    if size == "scalelength":
        return r
    if "psf_fwhm" not in tab.colnames:
        raise ShearfitIOError("the measured catalogue has no psf_fwhm column (written by shearfit measure since "
                              "version 0.1.0 of 2026-11-26): a resolution calibration needs it")
    with np.errstate(divide="ignore", invalid="ignore"):
        return r / np.asarray(tab["psf_fwhm"], float)


def model_m(snr, r, alpha, beta):
    """m(nu, r) = beta / ln(nu) exp(-alpha r nu)."""
    snr = np.asarray(snr, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return beta / np.log(snr) * np.exp(-alpha * np.asarray(r, float) * snr)


def calibration_m(snr, scalelength, alpha=PAPER_ALPHA, beta=PAPER_BETA):
    """m(nu, r) of eq. (alphabeta), r in arcsec; NaN where nu <= 1 or r is not finite."""
    snr = np.asarray(snr, float)
    r = np.asarray(scalelength, float)
    return np.where((snr > 1) & np.isfinite(r), model_m(np.where(snr > 1, snr, 2.0), r, alpha, beta), np.nan)


def _read(path, what):
    try:
        t = Table.read(path)
    except (OSError, ValueError) as exc:
        raise ShearfitIOError(f"{path}: cannot read the {what} table: {str(exc).splitlines()[0]}") from None
    t.rename_columns(t.colnames, [c.lower() for c in t.colnames])
    return t


def matched_galaxies(measured_path, truth_path, field=0) -> Table:
    """Measured galaxies joined to their truth rows by ``id`` (truth columns suffixed ``_true``).

    A metacal catalogue (``CALMODE = metacal``) enters with its ellipticities
    divided by its ensemble response (:func:`shearfit.calib.metacal.ensemble_response`),
    so that m and c are what remains after metacal.

    Adds ``e1_sh``, ``e2_sh`` (the true sheared ellipticity), ``field`` and
    ``group``: the truth header's ``SEED`` times 10^8 plus ``id``, so that a
    galaxy simulated with the same seed in several fields (same noise,
    another shear) is one group; without ``SEED`` every row is its own group.
    """
    m = _read(measured_path, "measured")
    t = _read(truth_path, "truth")
    for col in ("id", "e1", "e2", "weight", "fitclass", "snr", "scalelength"):
        if col not in m.colnames:
            raise ShearfitIOError(f"{measured_path}: no column {col}")
    for col in ("id", "g1", "g2", "e1_int", "e2_int", "is_star"):
        if col not in t.colnames:
            raise ShearfitIOError(f"{truth_path}: no column {col}")
    seed = t.meta.get("SEED", t.meta.get("seed"))
    if "r11" in m.colnames and str(m.meta.get("CALMODE", "")).lower() == "metacal":
        m = _metacal_corrected(m, measured_path)
    t = t[["id", "g1", "g2", "e1_int", "e2_int", "is_star"] + [c for c in ("snr", "scalelength") if c in t.colnames]]
    for c in ("snr", "scalelength"):
        if c in t.colnames:
            t.rename_column(c, f"{c}_true")
    j = join(m, t, keys="id")
    keep = (np.asarray(j["fitclass"]) == 0) & (np.asarray(j["weight"]) > 0) & ~np.asarray(j["is_star"], bool)
    keep &= np.isfinite(np.asarray(j["e1"], float)) & np.isfinite(np.asarray(j["snr"], float))
    keep &= np.asarray(j["snr"], float) > 1.0
    j = j[keep]
    es = sheared_ellipticity(np.asarray(j["e1_int"], float) + 1j * np.asarray(j["e2_int"], float),
                             np.asarray(j["g1"], float) + 1j * np.asarray(j["g2"], float))
    j["e1_sh"], j["e2_sh"] = es.real, es.imag
    j["field"] = np.full(len(j), int(field), dtype=np.int32)
    ids = np.asarray(j["id"], np.int64)
    if seed is None:
        j["group"] = (int(field) + 1) * -(10 ** 8) - ids       # unique per field: no noise shared
    else:
        j["group"] = int(seed) * 10 ** 8 + ids
    return j


def _metacal_corrected(m, path):
    """A metacal catalogue with e replaced by <R>^-1 e (its ensemble response, shear and selection)."""
    from .metacal import catalogue_response

    names = {f"r{i}{j}": f"R{i}{j}" for i in (1, 2) for j in (1, 2)}
    m = m.copy(copy_data=False)
    m.rename_columns(list(names), list(names.values()))
    R = catalogue_response(m, path)
    e = np.linalg.solve(R, np.stack([np.asarray(m["e1"], float), np.asarray(m["e2"], float)]))
    m["e1"], m["e2"] = e[0], e[1]
    m.meta["METACAL_R"] = R.tolist()
    return m


def sheared_ellipticity(e, g):
    """Complex ellipticity (a-b)/(a+b) after the reduced shear g: (e + g) / (1 + g* e)."""
    return (e + g) / (1 + np.conj(g) * e)


def stack_matched(pairs) -> Table:
    """:func:`matched_galaxies` of several (measured, truth) pairs, one table (``field`` = pair index)."""
    pairs = list(pairs)
    if not pairs:
        raise ShearfitValueError("no (measured, truth) pair to calibrate from")
    tabs = [matched_galaxies(m, t, field=k) for k, (m, t) in enumerate(pairs)]
    return vstack(tabs, metadata_conflicts="silent") if len(tabs) > 1 else tabs[0]


def _residuals(tab):
    """(y1, y2, g1, g2, w): measured minus true sheared ellipticity, shear and weight per galaxy."""
    col = lambda c: np.asarray(tab[c], float)  # noqa: E731
    return (col("e1") - col("e1_sh"), col("e2") - col("e2_sh"), col("g1"), col("g2"), col("weight"))


def _group_mean(codes, x):
    """Mean of ``x`` over each group (integer codes 0 .. n - 1; 0 for a code without rows)."""
    return np.bincount(codes, np.asarray(x, float)) / np.maximum(np.bincount(codes), 1)


def _group_codes(tab):
    """Group of each row as 0 .. n_groups - 1 (rows without a ``group`` column are their own group)."""
    if "group" not in tab.colnames:
        return np.arange(len(tab))
    return np.unique(np.asarray(tab["group"]), return_inverse=True)[1].ravel()


def bin_indices(snr, r, n_snr=20, n_size=20, min_per_bin=MIN_PER_BIN, groups=None):
    """Bin index (0 .. n_snr*n_size - 1) of each galaxy: equal numbers in SNR, then in size within each.

    With ``groups`` (an integer code per galaxy) whole groups are binned, by
    their members' mean SNR and size, and the counts are of groups. The bin
    counts shrink (keeping their ratio) until every bin has at least
    ``min_per_bin`` galaxies (groups). Returns (index, n_snr, n_size).
    """
    snr = np.asarray(snr, float)
    r = np.asarray(r, float)
    if groups is not None:
        groups = np.asarray(groups)
        present = np.bincount(groups) > 0
        gs, gr = _group_mean(groups, snr), _group_mean(groups, r)
        gidx = np.full(present.size, -1)
        gidx[present], n_snr, n_size = bin_indices(gs[present], gr[present], n_snr, n_size, min_per_bin)
        return gidx[groups], n_snr, n_size
    n = snr.size
    while n_snr * n_size * min_per_bin > n and (n_snr > 1 or n_size > 1):
        n_snr, n_size = max(1, n_snr - 1), max(1, n_size - 1)
    order = np.argsort(snr, kind="stable")
    ib = np.empty(n, int)
    ib[order] = np.arange(n) * n_snr // max(n, 1)
    idx = np.empty(n, int)
    for b in range(n_snr):
        sel = np.nonzero(ib == b)[0]
        o = sel[np.argsort(r[sel], kind="stable")]
        idx[o] = b * n_size + np.arange(o.size) * n_size // max(o.size, 1)
    return idx, n_snr, n_size


def _fit_mc(y1, y2, g1, g2, w):
    """Weighted least squares of y_k = m g_k + c_k over both components: (m, c1, c2)."""
    z = np.zeros_like(g1)
    one = np.ones_like(g1)
    X = np.concatenate([np.stack([g1, one, z], 1), np.stack([g2, z, one], 1)])
    y = np.concatenate([y1, y2])
    ww = np.sqrt(np.concatenate([w, w]))
    sol, *_ = np.linalg.lstsq(X * ww[:, None], y * ww, rcond=None)
    return sol


#: what a bootstrap draws: a galaxy with all its rows (its +g and -g copies), or a seed's fields with all their rows
RESAMPLE_UNITS = ("galaxies", "seeds")


def _resample_labels(tab, resample):
    """Per row, the unit the bootstrap draws (``resample``: ``galaxies`` or ``seeds``). A seed's fields share
    their PSFs and dithers, which move m from field to field by more than the galaxies' noise (about 0.02 on
    the closure's fields), so that only the seeds' bootstrap sees that scatter; rows without a seed are their
    own seed."""
    if resample not in RESAMPLE_UNITS:
        raise ShearfitValueError(f"resample {resample!r} is not one of {', '.join(RESAMPLE_UNITS)}")
    groups = _group_codes(tab)
    if resample == "galaxies":
        return groups
    seeds = _pair_codes(tab)
    return np.where(seeds >= 0, seeds, -1 - groups)


def _pair_codes(tab):
    """Per row, the seed whose fields it pairs within (``group`` // 10^8), or -1 for a group without a seed."""
    if "group" not in tab.colnames:
        return np.full(len(tab), -1, np.int64)
    g = np.asarray(tab["group"], np.int64)
    return np.where(g >= 0, g // 10 ** 8, -1)


def _complete_rows(g1, g2, w, groups, seeds):
    """Which rows enter :func:`_response_m`: those of groups with as many rows at +g as at -g, of a seed,
    weight > 0."""
    inv = np.unique(groups, return_inverse=True)[1].ravel()
    n = np.bincount(inv)
    s1, s2 = np.bincount(inv, g1), np.bincount(inv, g2)
    scale = np.bincount(inv, np.hypot(g1, g2)) / np.maximum(n, 1)
    complete = (n >= 2) & (np.hypot(s1, s2) < 1e-6 * np.maximum(scale, 1e-12) * n) & (scale > 0)
    return complete[inv] & (seeds >= 0) & (w > 0)


def _seed_means(e1, e2, g1, g2, w, groups, seeds):
    """Per seed, the weighted means of (e1, e2, g1, g2) over the rows :func:`_response_m` uses: the intercepts of
    its fit over the whole table, as {seed: array of 4}."""
    keep = _complete_rows(g1, g2, w, groups, seeds)
    out = {}
    if not keep.any():
        return out
    useeds, sk = np.unique(seeds[keep], return_inverse=True)
    W = np.bincount(sk.ravel(), w[keep])
    cols = [np.bincount(sk.ravel(), w[keep] * x[keep]) / W for x in (e1, e2, g1, g2)]
    for k, sd in enumerate(useeds.tolist()):
        out[sd] = np.array([c[k] for c in cols])
    return out


def _response_m(e1, e2, g1, g2, w, groups, seeds, means=None):
    """m of the weighted mean ellipticity's response to shear, from groups measured at opposite shears.

    A group (one galaxy with one noise, simulated at +g and -g) enters when it has as many rows at
    +g as at -g; in the weighted least-squares fit e_k = (1 + m) g_k + a_{s,k}, with an intercept per
    seed s and component k, its intrinsic shape then cancels between its rows in so far as their
    weights agree, and what remains is the response of the lensfit weights to the shear: a galaxy
    sheared along its major axis has a larger |e| and another weight at +g than at -g. The residual
    form y = e - e_s (:func:`_fit_mc`) removes that part with e_s, and misses it. None where no
    group is complete.

    ``means`` ({seed: the weighted means of e1, e2, g1, g2}, :func:`_seed_means` of the whole table): the
    intercepts held at the whole table's, so that a subset (a calibration bin) gives its part of the whole
    table's m: the whole's m is then the mean of its bins' m weighted by their sum(w |g|^2). With intercepts of
    its own, a bin with a few galaxies per seed would absorb in them part of the weights' response.
    """
    if groups.size == 0:
        return None
    keep = _complete_rows(g1, g2, w, groups, seeds)
    if not keep.any():
        return None
    e1, e2, g1, g2, w, seeds = e1[keep], e2[keep], g1[keep], g2[keep], w[keep], seeds[keep]
    useeds, sk = np.unique(seeds, return_inverse=True)
    sk = sk.ravel()
    if means is not None and all(sd in means for sd in useeds.tolist()):
        M = np.array([means[sd] for sd in useeds.tolist()])   # (seeds, 4)

        def centred(x, c):
            return x - M[sk, c]
    else:
        W = np.bincount(sk, w)

        def centred(x, c):
            return x - (np.bincount(sk, w * x) / W)[sk]

    dg1, dg2 = centred(g1, 2), centred(g2, 3)
    den = float(np.sum(w * (dg1 * dg1 + dg2 * dg2)))
    if not den > 0:
        return None
    return float(np.sum(w * (centred(e1, 0) * dg1 + centred(e2, 1) * dg2)) / den) - 1.0


def _fit_bias(y1, y2, g1, g2, w, e1, e2, groups, seeds, means=None):
    """(m, c1, c2): m from the weighted means' response (:func:`_response_m`, ``means`` its intercepts) where
    groups measured at +g and -g allow, else from the residuals' fit; c1, c2 from the residuals' fit
    (:func:`_fit_mc`)."""
    sol = _fit_mc(y1, y2, g1, g2, w)
    m = _response_m(e1, e2, g1, g2, w, groups, seeds, means)
    if m is not None:
        sol = np.array([m, sol[1], sol[2]])
    return sol


class _Bias:
    """The per-row inputs of :func:`_fit_bias` of a matched table, evaluated on row subsets (bins, bootstrap
    resamples) with the response's intercepts held at the whole table's (:func:`_seed_means`)."""

    def __init__(self, tab):
        self.y1, self.y2, self.g1, self.g2, self.w = _residuals(tab)
        self.e1, self.e2 = np.asarray(tab["e1"], float), np.asarray(tab["e2"], float)
        self.groups = np.asarray(tab["group"], np.int64) if "group" in tab.colnames else np.arange(len(tab))
        self.seeds = _pair_codes(tab)
        self.means = _seed_means(self.e1, self.e2, self.g1, self.g2, self.w, self.groups, self.seeds)

    def __call__(self, s):
        return _fit_bias(self.y1[s], self.y2[s], self.g1[s], self.g2[s], self.w[s], self.e1[s], self.e2[s],
                         self.groups[s], self.seeds[s], self.means)


def bin_bias(tab: Table, idx, n_bins, n_boot=100, rng=None, m_pred=None, resample="galaxies"):
    """Per bin: weighted mean SNR and size, m, c1, c2 with bootstrap errors (and the mean prediction).

    The bootstrap draws groups (see :func:`matched_galaxies`) with all their rows, or with ``resample="seeds"``
    the seeds present in the bin with all their rows (:func:`_resample_labels`).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    fit = _Bias(tab)
    w = fit.w
    groups = _resample_labels(tab, resample)
    snr, r = np.asarray(tab["snr"], float), np.asarray(tab["scalelength"], float)
    rows = []
    for b in range(n_bins):
        sel = np.nonzero(idx == b)[0]
        if sel.size < 3:
            continue
        est = fit(sel)
        boot = np.array([fit(s) for s in group_resamples(sel, groups, n_boot, rng)])
        # one unit (a single seed) has no scatter to resample: no error
        err = boot.std(axis=0) if np.unique(groups[sel]).size > 1 else np.full(boot.shape[1], np.nan)
        ws = w[sel] / w[sel].sum()
        row = dict(bin=b, n=int(sel.size), snr=float(np.sum(ws * snr[sel])), r=float(np.sum(ws * r[sel])),
                   weight=float(np.mean(w[sel])), m=float(est[0]), m_err=float(err[0]), c1=float(est[1]),
                   c1_err=float(err[1]), c2=float(est[2]), c2_err=float(err[2]))
        if m_pred is not None:
            mp = float(np.sum(ws * m_pred[sel]))
            row["m_pred"] = mp
            row["m_cal"] = float((1 + est[0]) / (1 + mp) - 1)
            row["m_cal_err"] = float(err[0] / abs(1 + mp))
        rows.append(row)
    if not rows:
        raise ShearfitValueError("no calibration bin has 3 galaxies")
    return Table(rows=[tuple(r.values()) for r in rows], names=list(rows[0].keys()))


def fit_alpha_beta(bins: Table, n_grid=81):
    """chi^2 fit of m(nu, r) to the bins, and the (alpha, beta) likelihood on a grid around the best fit."""
    snr, r, m, s = (np.asarray(bins[c], float) for c in ("snr", "r", "m", "m_err"))
    s = np.where(s > 0, s, np.inf)

    def resid(p):
        return (model_m(snr, r, p[0], p[1]) - m) / s

    sol = least_squares(resid, x0=[PAPER_ALPHA, PAPER_BETA], method="lm")
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((2, 2), np.nan)
    a0, b0 = sol.x
    sa = float(np.sqrt(abs(cov[0, 0]))) if np.isfinite(cov[0, 0]) else 0.05
    sb = float(np.sqrt(abs(cov[1, 1]))) if np.isfinite(cov[1, 1]) else 0.2
    alphas = np.linspace(max(a0 - 5 * sa, -0.5), a0 + 5 * sa, n_grid)
    betas = np.linspace(b0 - 5 * sb, b0 + 5 * sb, n_grid)
    A, B = np.meshgrid(alphas, betas, indexing="ij")
    pred = model_m(snr[None, None], r[None, None], A[..., None], B[..., None])
    chi2 = np.sum(((pred - m) / s) ** 2, axis=-1)
    loglike = -0.5 * (chi2 - chi2.min())
    return dict(alpha=float(a0), beta=float(b0), alpha_err=sa, beta_err=sb, cov=cov.tolist(),
                chi2=float(np.sum(resid(sol.x) ** 2)), dof=int(len(m) - 2),
                grid_alpha=alphas.tolist(), grid_beta=betas.tolist(), loglike=loglike.tolist())


def calibrate(pairs, n_snr=20, n_size=20, n_boot=100, seed=0, min_per_bin=MIN_PER_BIN, model="binned",
              size="scalelength", seeing_bins=1):
    """The calibration from simulated fields (see the module doc): (result dict, bins table, matched table).

    ``pairs``: a list of (measured catalogue, truth table) paths, one per field.
    ``model``: what the calibration applies, ``binned`` (the bins' m, looked
    up per galaxy) or ``paper`` (the fitted m = beta / ln(nu) exp(-alpha r nu));
    both are written. ``size``: the binned table's size axis, ``scalelength``
    (arcsec) or ``resolution`` (scalelength / psf_fwhm, which transfers to
    another seeing; see :class:`CalibrationModel`). ``seeing_bins`` > 1:
    also a table per range of the PSF's FWHM (``psf_fwhm``; ranges of equal
    numbers of galaxies), which the binned model applies in place of the
    one over all of them (``seeing`` in the result).
    """
    if model not in ("binned", "paper"):
        raise ShearfitValueError(f"calibration model {model!r} is not 'binned' or 'paper'")
    if size not in SIZE_MEASURES:
        raise ShearfitValueError(f"calibration size {size!r} is not one of {', '.join(SIZE_MEASURES)}")
    pairs = [tuple(p) for p in pairs]
    tab = stack_matched(pairs)
    names = ", ".join(str(m) for m, _ in pairs)
    if len(tab) < 3 * min_per_bin:
        raise ShearfitValueError(f"{names}: {len(tab)} measured galaxies match the truth; the calibration "
                                 f"needs at least {3 * min_per_bin}")
    if min(np.std(np.asarray(tab["g1"], float)), np.std(np.asarray(tab["g2"], float))) < 1e-4:
        raise ShearfitValueError(f"{', '.join(str(t) for _, t in pairs)}: the shear is the same for every galaxy; "
                                 "m and c cannot be separated (simulate with shear_rms > 0, or calibrate from "
                                 "fields with different shears)")
    if size == "resolution" or seeing_bins > 1:
        # the fields whose catalogues have no psf_fwhm (the stacked table masks their rows, or has no such column)
        if "psf_fwhm" not in tab.colnames:
            lacking = [str(m) for m, _ in pairs]
        else:
            masked = np.ma.getmaskarray(tab["psf_fwhm"])
            bad = set(np.asarray(tab["field"])[masked].tolist())
            lacking = [str(m) for k, (m, _) in enumerate(pairs) if k in bad]
        if lacking:
            raise ShearfitIOError(f"{', '.join(lacking)}: no column psf_fwhm, which a resolution calibration "
                                  "(size: resolution, scalelength / psf_fwhm) needs: measure again with this version, "
                                  "or calibrate with --size scalelength")
    groups = _group_codes(tab)
    sizes = size_values(tab, size)
    ok = np.isfinite(sizes)
    if not np.all(ok):   # a galaxy without a PSF size (its PSF's moments failed everywhere) cannot be binned
        tab = tab[ok]
        sizes = sizes[ok]
        groups = _group_codes(tab)
    idx, ns, nr = bin_indices(tab["snr"], sizes, n_snr, n_size, min_per_bin, groups=groups)
    rng = np.random.default_rng(seed)
    bins = bin_bias(tab, idx, ns * nr, n_boot, rng)
    fit = fit_alpha_beta(bins)
    tot = _Bias(tab)(np.arange(len(tab)))
    binned = binned_table(tab, idx, ns, nr, bins, groups, sizes)
    seeing = _seeing_tables(tab, groups, sizes, seeing_bins, n_snr, n_size, n_boot, min_per_bin, rng) \
        if seeing_bins > 1 else None
    result = dict(fit, n_galaxies=int(len(tab)), n_groups=int(groups.max() + 1), n_snr_bins=int(ns),
                  n_size_bins=int(nr), m_raw=float(tot[0]), c1=float(tot[1]), c2=float(tot[2]),
                  paper_alpha=PAPER_ALPHA, paper_beta=PAPER_BETA, model=model, size=size, binned=binned,
                  measured=[str(m) for m, _ in pairs], truth=[str(t) for _, t in pairs])
    if seeing is not None:
        result["seeing"] = seeing
    return result, bins, tab


def _seeing_tables(tab, groups, sizes, n_ranges, n_snr, n_size, n_boot, min_per_bin, rng):
    """Binned tables per range of the PSF's FWHM (galaxies' group means; ranges of equal numbers of groups):
    {psf_edges, tables, n_galaxies}."""
    gpsf = _group_mean(groups, tab["psf_fwhm"])
    edges = [float(v) for v in np.quantile(gpsf[np.bincount(groups) > 0], np.arange(1, n_ranges) / n_ranges)]
    rng_of = np.searchsorted(np.asarray(edges), gpsf)[groups]
    tables, counts = [], []
    for k in range(n_ranges):
        sel = np.nonzero(rng_of == k)[0]
        sub = tab[sel]
        gsub = _group_codes(sub)
        idx, ns, nr = bin_indices(sub["snr"], sizes[sel], n_snr, n_size, min_per_bin, groups=gsub)
        bins = bin_bias(sub, idx, ns * nr, n_boot, rng)
        tables.append(binned_table(sub, idx, ns, nr, bins, gsub, sizes[sel]))
        counts.append(int(sel.size))
    return dict(psf_edges=edges, tables=tables, n_galaxies=counts)


def binned_table(tab, idx, n_snr, n_size, bins, groups, sizes=None):
    """The bins as a look-up table: SNR edges, size edges within each SNR bin, m and its error per bin.

    Edges lie half-way between neighbouring bins' groups (mean SNR, then mean size within the SNR bin);
    ``sizes``: the size axis per row (default the scalelength).
    """
    codes = np.asarray(groups)
    gs = _group_mean(codes, tab["snr"])
    gr = _group_mean(codes, tab["scalelength"] if sizes is None else sizes)
    gidx = np.full(gs.size, -1)
    gidx[codes] = idx
    snr_bin, size_bin = gidx // n_size, gidx % n_size
    snr_edges = [0.5 * (gs[snr_bin == b].max() + gs[snr_bin == b + 1].min()) for b in range(n_snr - 1)]
    size_edges = []
    for b in range(n_snr):
        rb, sb = gr[snr_bin == b], size_bin[snr_bin == b]
        size_edges.append([0.5 * (rb[sb == k].max() + rb[sb == k + 1].min()) for k in range(n_size - 1)])
    m = np.full((n_snr, n_size), np.nan)
    merr = np.full((n_snr, n_size), np.nan)
    for row in bins:
        m[row["bin"] // n_size, row["bin"] % n_size] = row["m"]
        merr[row["bin"] // n_size, row["bin"] % n_size] = row["m_err"]
    return dict(snr_edges=[float(x) for x in snr_edges], size_edges=[[float(x) for x in e] for e in size_edges],
                m=np.nan_to_num(m).tolist(), m_err=np.nan_to_num(merr, nan=1.0).tolist())


def _table_m(b, snr, x):
    """m of a binned table ``b`` (snr_edges, size_edges per SNR bin, m) at (snr, size x); outside it, the nearest
    bin."""
    m_tab = np.asarray(b["m"], float)
    ib = np.searchsorted(np.asarray(b["snr_edges"], float), snr)
    out = np.full(snr.shape, np.nan)
    for k in range(m_tab.shape[0]):
        sel = ib == k
        if np.any(sel):
            jb = np.searchsorted(np.asarray(b["size_edges"][k], float), x[sel])
            out[sel] = m_tab[k, jb]
    return out


class CalibrationModel:
    """m(SNR, size) of a calibration: the paper's form with (alpha, beta), or the binned table.

    ``kind`` ``paper``: eq. (alphabeta), r the scalelength in arcsec. ``binned``: the m of the SNR-size bin a
    galaxy falls in (bins of ``shearfit calibrate``; outside the table, the nearest bin), its size measured as
    ``size`` says: ``scalelength`` (arcsec, the paper's) or ``resolution``, the scalelength over the PSF's FWHM
    at the object (the catalogue's ``psf_fwhm``), which carries the table to a survey of another seeing.
    ``seeing`` ({psf_edges, tables}): tables fitted in ranges of the PSF's FWHM (arcsec, edges between them),
    each applied to the galaxies of its range (below the first edge the first, above the last the last) in
    place of ``binned``, which then holds the table fitted on all of them.
    ``draws(n, rng)`` gives ``n`` models drawn from the calibration's uncertainty (the (alpha, beta)
    likelihood grid, or each bin's m within its bootstrap error) for the systematic covariance.
    """

    def __init__(self, alpha=PAPER_ALPHA, beta=PAPER_BETA, kind="paper", binned=None, grid=None, size="scalelength",
                 seeing=None):
        if kind not in ("paper", "binned"):
            raise ShearfitValueError(f"calibration model {kind!r} is not 'paper' or 'binned'")
        if kind == "binned" and binned is None:
            raise ShearfitValueError("a binned calibration needs its table")
        if size not in SIZE_MEASURES:
            raise ShearfitValueError(f"calibration size {size!r} is not one of {', '.join(SIZE_MEASURES)}")
        self.alpha, self.beta, self.kind, self.binned, self.grid = float(alpha), float(beta), kind, binned, grid
        self.size = size if kind == "binned" else "scalelength"
        self.seeing = seeing if kind == "binned" else None

    def m(self, snr, scalelength, psf_fwhm=None):
        """m per galaxy (NaN where SNR <= 1 or the size is not finite); ``psf_fwhm`` (arcsec) is needed by a
        table of ``size: resolution`` or with ``seeing`` ranges."""
        snr = np.asarray(snr, float)
        r = np.asarray(scalelength, float)
        if self.kind == "paper":
            return calibration_m(snr, r, self.alpha, self.beta)
        if (self.size == "resolution" or self.seeing) and psf_fwhm is None:
            raise ShearfitValueError("this calibration's sizes are resolutions (scalelength / psf_fwhm) or its tables "
                                     "are per seeing: it needs the catalogue's psf_fwhm column")
        psf = None if psf_fwhm is None else np.broadcast_to(np.asarray(psf_fwhm, float), r.shape)
        x = r
        if self.size == "resolution":
            with np.errstate(divide="ignore", invalid="ignore"):
                x = r / psf
        if self.seeing:
            tables = self.seeing["tables"]
            ip = np.searchsorted(np.asarray(self.seeing["psf_edges"], float), np.nan_to_num(psf, nan=np.inf))
            out = np.full(snr.shape, np.nan)
            for k, b in enumerate(tables):
                sel = (ip == k) if k < len(tables) - 1 else (ip >= k)
                if np.any(sel):
                    out[sel] = _table_m(b, snr[sel], x[sel])
            out = np.where(np.isfinite(psf), out, np.nan)
        else:
            out = _table_m(self.binned, snr, x)
        return np.where(np.isfinite(snr) & np.isfinite(x) & (snr > 1), out, np.nan)

    def m_of(self, tab):
        """m of a catalogue or matched table's rows (its snr, scalelength and, if present, psf_fwhm): an astropy
        Table or a numpy structured array."""
        names = tab.colnames if hasattr(tab, "colnames") else tab.dtype.names
        psf = np.asarray(tab["psf_fwhm"], float) if "psf_fwhm" in names else None
        return self.m(np.asarray(tab["snr"], float), np.asarray(tab["scalelength"], float), psf)

    def draws(self, n, rng):
        if self.kind == "paper":
            if self.grid is None:
                raise ShearfitValueError("the calibration has no likelihood grid to draw from")
            a_s, b_s = _grid_samples(*self.grid, n, rng)
            return [CalibrationModel(a, b) for a, b in zip(a_s, b_s)]

        def drawn(b):
            m = np.asarray(b["m"], float)
            e = np.asarray(b["m_err"], float)
            return dict(b, m=(m + e * rng.normal(size=m.shape)).tolist())

        out = []
        for _ in range(n):
            seeing = None if not self.seeing else dict(self.seeing, tables=[drawn(b) for b in self.seeing["tables"]])
            out.append(CalibrationModel(self.alpha, self.beta, "binned", drawn(self.binned), size=self.size,
                                        seeing=seeing))
        return out


def as_model(calibration) -> CalibrationModel:
    """A CalibrationModel from a model, an (alpha, beta) pair or a calibration file's path."""
    if isinstance(calibration, CalibrationModel):
        return calibration
    if isinstance(calibration, (tuple, list)) and len(calibration) == 2:
        return CalibrationModel(*calibration)
    return load_calibration(calibration)


def load_calibration(path) -> CalibrationModel:
    """The model of a calibration.yaml (``model: binned`` or ``paper``; files without ``model`` are ``paper``)."""
    d = read_yaml_mapping(path, "calibration")
    alpha, beta = _alpha_beta(path, d)
    kind = str(d.get("model", "paper")).lower()
    grid = None
    if all(k in d for k in ("grid_alpha", "grid_beta", "loglike")):
        grid = _checked_grid(path, d)
    binned = d.get("binned")
    seeing = d.get("seeing")
    if kind == "binned":
        if not _table_ok(binned):
            raise ShearfitIOError(f"{path}: calibration model binned needs a consistent 'binned' table "
                                  "(snr_edges, size_edges, m, m_err)")
        if seeing is not None:
            try:
                tables, edges = list(seeing["tables"]), [float(v) for v in seeing["psf_edges"]]
                ok = len(tables) == len(edges) + 1 and all(_table_ok(b) for b in tables) and np.all(np.diff(edges) > 0)
            except (TypeError, KeyError, ValueError):
                ok = False
            if not ok:
                raise ShearfitIOError(f"{path}: calibration key 'seeing' needs psf_edges and one consistent table "
                                      "more than edges")
    elif kind != "paper":
        raise ShearfitIOError(f"{path}: calibration key 'model' must be 'paper' or 'binned', not {kind!r}")
    size = str(d.get("size", "scalelength")).lower()
    if size not in SIZE_MEASURES:
        raise ShearfitIOError(f"{path}: calibration key 'size' must be one of {', '.join(SIZE_MEASURES)}, not {size!r}")
    return CalibrationModel(alpha, beta, kind, binned if kind == "binned" else None, grid, size=size,
                            seeing=seeing if kind == "binned" else None)


def _table_ok(binned):
    """Whether a binned table's parts agree (edges, m and m_err of matching shapes)."""
    try:
        ns = len(binned["snr_edges"]) + 1
        m = np.asarray(binned["m"], float)
        me = np.asarray(binned["m_err"], float)
        return bool(m.ndim == 2 and m.shape[0] == ns and me.shape == m.shape and len(binned["size_edges"]) == ns
                    and all(len(e) == m.shape[1] - 1 for e in binned["size_edges"]))
    except (TypeError, KeyError, ValueError):
        return False


#: The calibration ``shearfit measure`` applies where the field configuration names none: the m of each SNR-size
#: bin fitted on shearfit's own GREAT-like simulated fields with the engine's default settings
#: (``benchmarks/calibration_closure.py --write-default``; the file records the command, the settings and the
#: closure on held-out fields). The paper's (alpha, beta) were fitted for the CFHTLenS pipeline and leave m of
#: several per cent on this engine's simulations.
DEFAULT_CALIBRATION = os.path.join(os.path.dirname(os.path.abspath(__file__)), "default_calibration.yaml")
#: The same for fits with ``self_calibration: true``, whose noise bias differs (fitted on the same fields with
#: that setting in force: ``benchmarks/calibration_closure.py --set self_calibration=true --write-default``).
DEFAULT_CALIBRATION_SELFCAL = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                           "default_calibration_selfcal.yaml")


def default_calibration(self_calibration: bool = False) -> CalibrationModel:
    """The model of :data:`DEFAULT_CALIBRATION`, or of :data:`DEFAULT_CALIBRATION_SELFCAL` for fits made with
    ``self_calibration``."""
    return load_calibration(DEFAULT_CALIBRATION_SELFCAL if self_calibration else DEFAULT_CALIBRATION)


def default_calibration_record(result, source, closure=None) -> dict:
    """What :data:`DEFAULT_CALIBRATION` keeps of a :func:`calibrate` result: the binned table, the fitted
    (alpha, beta) with their errors, the sample's size, ``source`` (how it was made) and ``closure`` (what
    it leaves on held-out fields)."""
    keep = ("alpha", "beta", "alpha_err", "beta_err", "chi2", "dof", "n_galaxies", "n_groups", "n_snr_bins",
            "n_size_bins", "paper_alpha", "paper_beta", "model", "size", "binned", "seeing")
    out = {k: result[k] for k in keep if k in result}
    out["source"] = str(source)
    if closure is not None:
        out["closure"] = closure
    return out


def write_calibration(result, path):
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write("# shearfit noise-bias calibration. model: binned applies the m of each SNR-size bin (binned:; size: "
                "scalelength in arcsec or resolution = scalelength / psf_fwhm), paper the fit "
                "m(nu, r) = beta / ln(nu) exp(-alpha r nu), r in arcsec\n")
        yaml.safe_dump(result, f, sort_keys=False, default_flow_style=None)


def read_calibration(path):
    """(alpha, beta) of a calibration.yaml."""
    return _alpha_beta(path, read_yaml_mapping(path, "calibration"))


def _alpha_beta(path, d):
    for k in ("alpha", "beta"):
        if k not in d:
            raise ShearfitIOError(f"{path}: calibration has no key {k!r}")
        try:
            d[k] = float(d[k])
        except (TypeError, ValueError):
            raise ShearfitIOError(f"{path}: calibration key {k!r} is not a number: {d[k]!r}") from None
    return d["alpha"], d["beta"]


def _checked_grid(path, d):
    try:
        ga = np.asarray(d["grid_alpha"], float)
        gb = np.asarray(d["grid_beta"], float)
        ll = np.asarray(d["loglike"], float)
    except KeyError as exc:
        raise ShearfitIOError(f"{path}: calibration has no likelihood grid (key {exc.args[0]!r}); "
                              "one written by shearfit calibrate has it") from None
    except (TypeError, ValueError):
        raise ShearfitIOError(f"{path}: calibration likelihood grid is not numeric") from None
    if ll.shape != (ga.size, gb.size) or ga.size < 2 or gb.size < 2 or not np.all(np.isfinite(ll)):
        raise ShearfitIOError(f"{path}: calibration loglike must be a finite {ga.size} x {gb.size} grid")
    return ga, gb, ll


def _grid_samples(ga, gb, ll, n, rng):
    p = np.exp(ll - ll.max()).ravel()
    k = rng.choice(p.size, size=n, p=p / p.sum())
    ia, ib = np.unravel_index(k, ll.shape)
    da, db = ga[1] - ga[0], gb[1] - gb[0]
    return ga[ia] + da * rng.uniform(-0.5, 0.5, n), gb[ib] + db * rng.uniform(-0.5, 0.5, n)


def calibration_samples(path, n, rng):
    """``n`` (alpha, beta) pairs drawn from a calibration file's likelihood grid (uniform within each cell).

    The systematic covariance of calibrated two-point functions (sec. 8.5)
    propagates these draws. Files without the grid are refused.
    """
    d = read_yaml_mapping(path, "calibration")
    return _grid_samples(*_checked_grid(path, d), n, rng)


def calibrated_bias(tab: Table, calibration, n_boot=200, seed=0, resample="galaxies"):
    """Overall m, c1, c2 of a matched table before and after a calibration, with errors.

    ``calibration``: a :class:`CalibrationModel`, an (alpha, beta) pair or a calibration file.

    The calibration divides the weighted shear estimate by 1 + the weighted mean m of the
    galaxies (the paper's ensemble correction), so the calibrated m is (1 + m_raw) / (1 + <m>) - 1.
    Errors (``*_err``) from a bootstrap over groups (see :func:`matched_galaxies`), or with
    ``resample="seeds"`` over the seeds (:func:`_resample_labels`).
    """
    fit = _Bias(tab)
    w = fit.w
    mc = as_model(calibration).m_of(tab)
    mc = np.where(np.isfinite(mc), mc, 0.0)

    def est(s):
        raw = fit(s)
        mbar = float(np.sum(w[s] * mc[s]) / np.sum(w[s]))
        return np.array([raw[0], raw[1], raw[2], mbar, (1 + raw[0]) / (1 + mbar) - 1])

    rows = np.arange(len(tab))
    full = est(rows)
    labels = _resample_labels(tab, resample)
    boot = np.array([est(s) for s in group_resamples(rows, labels, n_boot, np.random.default_rng(seed))])
    # one unit (a single seed) has no scatter to resample: no error
    err = boot.std(axis=0) if np.unique(labels).size > 1 else np.full(boot.shape[1], np.nan)
    names = ("m_raw", "c1", "c2", "m_mean", "m_cal")
    out = {k: float(v) for k, v in zip(names, full)}
    out.update({f"{k}_err": float(v) for k, v in zip(names, err)})
    out["n_galaxies"] = int(len(tab))
    return out


def plot_calibration(bins: Table, result, path, weight_bins=None):
    """m against SNR and size per bin with the fitted and the paper's m(nu, r), and m against weight."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    snr, r, m, s = (np.asarray(bins[c], float) for c in ("snr", "r", "m", "m_err"))
    sc = ax[0].scatter(snr, m, c=r, s=12, cmap="viridis")
    ax[0].errorbar(snr, m, s, fmt="none", ecolor="0.7", lw=0.5, zorder=0)
    xs = np.geomspace(max(snr.min(), 2), snr.max(), 100)
    for rr in np.percentile(r, [10, 50, 90]):
        ax[0].plot(xs, model_m(xs, rr, result["alpha"], result["beta"]), "-", lw=1, label=f"fit, r = {rr:.2f}\"")
        ax[0].plot(xs, model_m(xs, rr, PAPER_ALPHA, PAPER_BETA), ":", lw=1)
    ax[0].set_xscale("log")
    ax[0].set_xlabel("SNR")
    ax[0].set_ylabel("m")
    ax[0].axhline(0, color="k", lw=0.5)
    ax[0].legend(fontsize=7, title="dotted: paper (0.057, -0.37)", title_fontsize=7)
    fig.colorbar(sc, ax=ax[0], label="scalelength (arcsec)")
    ax[1].scatter(r, m, c=np.log10(snr), s=12, cmap="plasma")
    ax[1].errorbar(r, m, s, fmt="none", ecolor="0.7", lw=0.5, zorder=0)
    ax[1].set_xlabel("scalelength (arcsec)")
    ax[1].set_ylabel("m")
    ax[1].axhline(0, color="k", lw=0.5)
    if weight_bins is not None:
        wb = weight_bins
        ax[2].errorbar(wb["weight"], wb["m"], wb["m_err"], fmt="o", ms=3, label="raw")
        if "m_pred" in wb.colnames:
            ax[2].plot(wb["weight"], wb["m_pred"], "-", label="calibration m(nu, r)")
        ax[2].set_xlabel("mean lensfit weight")
        ax[2].set_ylabel("m")
        ax[2].axhline(0, color="k", lw=0.5)
        ax[2].legend(fontsize=8)
    fig.suptitle(f"alpha = {result['alpha']:.3f} +- {result['alpha_err']:.3f}, beta = {result['beta']:.3f} +- "
                 f"{result['beta_err']:.3f} ({result['n_galaxies']} galaxies)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def weight_bins(tab: Table, calibration, n=10, n_boot=100, seed=0):
    """m in bins of lensfit weight (equal numbers), with the calibration's mean prediction per bin."""
    return quantity_bins(tab, "weight", calibration, n=n, n_boot=n_boot, seed=seed)


def quantity_bins(tab: Table, column, calibration, n=6, n_boot=100, seed=0, resample="galaxies"):
    """Raw and calibrated m (and c) in equal-number bins of one column (``snr``, ``scalelength``, ...).

    Groups are binned by their mean value, so the copies of a galaxy stay together. ``resample``: the
    bootstrap's unit, ``galaxies`` or ``seeds`` (:func:`bin_bias`).
    """
    codes = _group_codes(tab)
    gx = _group_mean(codes, tab[column])
    order = np.argsort(gx, kind="stable")
    gidx = np.empty(gx.size, int)
    gidx[order] = np.arange(gx.size) * n // max(gx.size, 1)
    pred = as_model(calibration).m_of(tab)
    pred = np.where(np.isfinite(pred), pred, 0.0)
    idx = gidx[codes]
    out = bin_bias(tab, idx, n, n_boot, np.random.default_rng(seed), m_pred=pred, resample=resample)
    # the weighted mean of the binned quantity itself, per bin (column x)
    w, x = np.asarray(tab["weight"], float), np.asarray(tab[column], float)
    out["x"] = [float(np.sum(w[idx == b] * x[idx == b]) / np.sum(w[idx == b])) for b in out["bin"]]
    return out
