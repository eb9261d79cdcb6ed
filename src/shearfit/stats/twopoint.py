"""Calibrated shear two-point functions (sec. 8.5): ``shearfit xipm``.

xi+ and xi- of the lensfit-weighted ellipticities come from TreeCorr's
``GGCorrelation`` (the catalogue's e1, e2 are in TreeCorr's convention, see
docs/interface.rst). The multiplicative calibration enters as the paper's
ensemble correction: with m_i the calibration of galaxy i,

    1 + K(theta) = sum_ij w_i w_j (1 + m_i)(1 + m_j) / sum_ij w_i w_j

over the pairs of each bin (TreeCorr's ``KKCorrelation`` of k = 1 + m with
the same weights), and xi_cal = xi / (1 + K). The systematic covariance of
xi_cal comes from recomputing m_i, and so 1 + K, for (alpha, beta) pairs
drawn from the calibration's likelihood.

Tomographic bins (``--bins COLUMN:EDGES``): xi+- of every pair (i <= j) of
bins, 1 + K across the two bins, sum_ab w_a w_b (1 + m_a)(1 + m_b) /
sum_ab w_a w_b with a in bin i and b in bin j. ``--patches N``: the
jackknife covariance over N TreeCorr (k-means) patches of the calibrated
data vector, the pairs' (xip, xim) concatenated in :func:`bin_pairs`' order.
"""

from __future__ import annotations

import numpy as np
import treecorr
from astropy.table import Table

from ..calib.calibrate import load_calibration
from ..errors import ShearfitIOError, ShearfitValueError

__all__ = ["read_shear_catalog", "measured", "parse_selection", "parse_bins", "split_bins", "bin_pairs", "xipm",
           "xipm_bins", "write_xipm", "write_xipm_file", "plot_xipm", "metacal_response_of", "DEFAULT_BIN_SLOP",
           "DEFAULT_ANGLE_SLOP"]

# TreeCorr's exact pair binning: its own default (0.1 / bin size, ~0.22 for 10 bins over 1-100 arcmin) moves xi+
# by up to ~0.6-0.9 shape-noise sigma on a 10^4-galaxy square degree, and even 0.02 by > 0.1 sigma
# (benchmarks/xipm_binning.py); bin_slop = 0 costs ~5x TreeCorr's default there (~0.6 s).
DEFAULT_BIN_SLOP = 0.0
# and a near-exact projection: with bin_slop = 0, TreeCorr still projects a pair's shears along the line between
# its cells' centres to within angle_slop (its default 0.1 rad), which moves xi- by up to 0.2 sigma from brute
# force on that field; 0.02 keeps it within 0.03 sigma at about twice the time of 0.1, while 0 is brute force
# itself (every cell split to its points: N^2, 10x the time at 10^4 galaxies, unaffordable for a survey)
DEFAULT_ANGLE_SLOP = 0.02

_NEEDED = ("ra", "dec", "e1", "e2", "weight", "fitclass")


def parse_selection(text):
    """``COLUMN:MIN:MAX`` (either bound may be empty) -> (column, lo, hi)."""
    parts = str(text).split(":")
    if len(parts) != 3 or not parts[0]:
        raise ShearfitValueError(f"selection {text!r}: expected COLUMN:MIN:MAX (e.g. z_b:0.5:0.85)")
    try:
        lo = float(parts[1]) if parts[1] else -np.inf
        hi = float(parts[2]) if parts[2] else np.inf
    except ValueError:
        raise ShearfitValueError(f"selection {text!r}: MIN and MAX must be numbers") from None
    return parts[0], lo, hi


def read_shear_catalog(path, selections=(), extra=None, measured_only=True, weight_column="weight") -> Table:
    """The measured galaxies of a shearfit catalogue (fitclass 0, weight > 0, finite e), after the selections.

    ``selections``: (column, lo, hi) ranges, e.g. a tomographic bin of a
    photometric-redshift column joined to the catalogue beforehand.
    ``measured_only=False`` keeps every object that passes the selections
    (a metacal selection response needs the objects that only the sheared
    versions select); :func:`measured` takes the galaxies from it.
    ``weight_column``: the column whose values are the weights (``iso_weight``, say: it is copied into
    ``weight``, and lensfit's is kept as ``lensfit_weight``). A metacal catalogue keeps its own weights: its
    selection response is measured with the sheared versions' ``weight_1p`` ...
    """
    try:
        t = Table.read(path)
    except (OSError, ValueError) as exc:
        raise ShearfitIOError(f"{path}: cannot read the shear catalogue: {str(exc).splitlines()[0]}") from None
    for col in tuple(_NEEDED) + tuple(extra or ()) + (weight_column,):
        if col not in t.colnames:
            raise ShearfitIOError(f"{path}: shear catalogue has no column {col!r}")
    if weight_column != "weight":
        if "weight_1p" in t.colnames:
            raise ShearfitValueError(f"{path}: a metacal catalogue: its weights are 'weight' and the sheared "
                                     f"versions' (the selection response), not {weight_column!r}")
        t["lensfit_weight"] = t["weight"]
        t["weight"] = np.asarray(t[weight_column], float)
    keep = np.ones(len(t), bool)
    for col, lo, hi in selections:
        if col not in t.colnames:
            raise ShearfitIOError(f"{path}: selection column {col!r} is not in the catalogue")
        v = np.asarray(t[col], float)
        keep &= (v >= lo) & (v < hi)
    t = t[keep]
    return measured(t) if measured_only else t


def measured(t: Table) -> Table:
    """The rows of a shear catalogue that are measured galaxies (fitclass 0, weight > 0, finite e)."""
    keep = (np.asarray(t["fitclass"]) == 0) & (np.asarray(t["weight"], float) > 0)
    keep &= np.isfinite(np.asarray(t["e1"], float)) & np.isfinite(np.asarray(t["e2"], float))
    return t[keep]


def metacal_response_of(full: Table, source):
    """The ensemble metacal response (2x2: shear and selection parts) of a catalogue's selected objects.

    ``full``: every object that passes the selections (``read_shear_catalog(...,
    measured_only=False)``). None for a catalogue without metacal columns
    (see :mod:`shearfit.calib.metacal`).
    """
    from ..calib.metacal import catalogue_response

    if "R11" not in full.colnames or str(full.meta.get("CALMODE", "metacal")).lower() != "metacal":
        return None
    return catalogue_response(full, source)


def parse_bins(text):
    """``COLUMN:EDGES`` (e.g. ``z_b:0.2,0.5,0.9`` or ``zbin:0,1,2``) -> (column, edges): bin k is
    edges[k] <= COLUMN < edges[k + 1], as ``--select``'s ranges."""
    col, sep, rest = str(text).partition(":")
    if not sep or not col or not rest:
        raise ShearfitValueError(f"--bins {text!r}: expected COLUMN:EDGES (e.g. z_b:0.2,0.5,0.9,1.3)")
    try:
        edges = np.array([float(x) for x in rest.split(",")])
    except ValueError:
        raise ShearfitValueError(f"--bins {text!r}: the edges must be numbers separated by commas") from None
    if len(edges) < 2:
        raise ShearfitValueError(f"--bins {text!r}: at least two edges (one bin) are needed")
    if not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
        raise ShearfitValueError(f"--bins {text!r}: the edges must be finite and increasing")
    return col, edges


def split_bins(tab: Table, column, edges, source="catalogue"):
    """The rows of ``tab`` in each bin edges[k] <= column < edges[k + 1] (a list of tables)."""
    if column not in tab.colnames:
        raise ShearfitIOError(f"{source}: --bins column {column!r} is not in the catalogue")
    v = np.asarray(tab[column], float)
    return [tab[(v >= lo) & (v < hi)] for lo, hi in zip(edges[:-1], edges[1:])]


def bin_pairs(nbin):
    """The (i, j), i <= j, pairs of ``nbin`` bins in the order of the files and the data vector:
    (0, 0), (0, 1), ..., (0, n-1), (1, 1), ..., (n-1, n-1)."""
    return [(i, j) for i in range(nbin) for j in range(i, nbin)]


def _catalog(tab, k, with_shear=True, patch_centers=None):
    """TreeCorr catalogue of the galaxies' positions and weights, with k (and the ellipticities)."""
    cols = dict(ra=np.asarray(tab["ra"], float), dec=np.asarray(tab["dec"], float), ra_units="deg",
                dec_units="deg", w=np.asarray(tab["weight"], float), k=k)
    if with_shear:
        cols.update(g1=np.asarray(tab["e1"], float), g2=np.asarray(tab["e2"], float))
    if patch_centers is not None:
        cols["patch_centers"] = patch_centers
    return treecorr.Catalog(**cols)


def _process(corr, cats, i, j):
    """``corr`` processed for the pair (i, j) of catalogues: the auto-correlation of i, or i x j."""
    two = () if i == j else (cats[j],)
    if isinstance(corr, treecorr.KKCorrelation):
        # 1 + K needs no variance of k: TreeCorr's (summed over patches) can round below 0 for a constant k,
        # and its log line takes the square root of it; finalize with 0 instead
        corr.process(cats[i], *two, finalize=False)
        corr.finalize(0.0, 0.0)
    else:
        corr.process(cats[i], *two)
    return corr


def _calibrated(gg, kk):
    """(xip, xim) / (1 + K), NaN where a bin has no pairs (used for the data and each jackknife sample)."""
    ok = kk.weight > 0
    opk = np.where(ok, kk.xi, np.nan)
    return gg.xip / opk, gg.xim / opk


def xipm_bins(tabs, min_sep=1.0, max_sep=100.0, nbins=10, calibration=None, n_sys=100, seed=0,
              bin_slop=DEFAULT_BIN_SLOP, responses=None, npatch=0, names=None, angle_slop=DEFAULT_ANGLE_SLOP):
    """xi+- of every auto and cross pair of the samples ``tabs`` (tomographic bins), calibrated per pair.

    For the pair (i, j), 1 + K is the weighted pair average of (1 + m_a)(1 + m_b), a in bin i and b in
    bin j (TreeCorr's ``KKCorrelation`` of k = 1 + m across the two bins; for i = j the single-sample
    1 + K); m as in :func:`xipm`, ``responses`` one metacal response (or None) per bin. Returns (list of
    ((i, j), table) in :func:`bin_pairs`' order, systematic covariance or None, jackknife covariance or
    None). The covariances are of the data vector (xip, xim) of the first pair, then of the second, ...
    ``npatch`` >= 2: TreeCorr patches (k-means on the positions of all the samples together, its random
    generator seeded by ``seed``) and the jackknife covariance of the calibrated data vector (pairs
    crossing patches weighted by MP22's "match"); each table then has ``sigma_xip_jk``, ``sigma_xim_jk``.
    ``angle_slop``: TreeCorr's (default 0.02 rad; None: TreeCorr's own, 0.1): how far the direction along which
    a pair's shears are projected may be from the pair's own, bin_slop = 0 notwithstanding (0: brute force,
    N^2; 0.1 moves xi- by up to 0.2 sigma, 0.02 by 0.03: benchmarks/xipm_binning.py).
    """
    nb = len(tabs)
    names = list(names) if names is not None else [f"bin {i}" for i in range(nb)]
    responses = list(responses) if responses is not None else [None] * nb
    for t, name in zip(tabs, names):
        if len(t) < 2:
            raise ShearfitValueError(f"{name}: {len(t)} measured galaxies: two-point functions need at least 2")
    model = load_calibration(calibration) if calibration is not None else None
    ms = []
    for t, R in zip(tabs, responses):
        if model is not None:
            if "snr" not in t.colnames or "scalelength" not in t.colnames:
                raise ShearfitIOError("the catalogue needs snr and scalelength columns to apply a calibration file")
            m = model.m_of(t)
        elif R is not None:
            m = np.full(len(t), 0.5 * (R[0][0] + R[1][1]) - 1.0)
        elif "m" in t.colnames:
            m = np.asarray(t["m"], float)
        else:
            m = np.zeros(len(t))
        ms.append(np.where(np.isfinite(m), m, 0.0))
    centers = None
    if npatch:
        ntot = sum(len(t) for t in tabs)
        if not 2 <= npatch <= ntot:
            raise ShearfitValueError(f"--patches {npatch}: a jackknife needs 2 to {ntot} (the galaxies) patches")
        allpos = Table({c: np.concatenate([np.asarray(t[c], float) for t in tabs]) for c in ("ra", "dec", "weight")})
        centers = treecorr.Catalog(ra=allpos["ra"], dec=allpos["dec"], w=allpos["weight"], ra_units="deg",
                                   dec_units="deg", npatch=npatch, rng=np.random.default_rng(seed)).patch_centers
    cats = [_catalog(t, 1.0 + m, patch_centers=centers) for t, m in zip(tabs, ms)]
    cfg = dict(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units="arcmin", bin_slop=bin_slop)
    if angle_slop is not None:
        cfg["angle_slop"] = angle_slop
    pairs, corrs = bin_pairs(nb), []
    out = []
    for i, j in pairs:
        gg = _process(treecorr.GGCorrelation(**cfg), cats, i, j)
        kk = _process(treecorr.KKCorrelation(**cfg), cats, i, j)
        corrs += [gg, kk]
        # a bin without pairs (wider than the field) is NaN throughout, its theta the nominal one
        empty = gg.npairs == 0
        one_plus_k = np.where(empty, np.nan, kk.xi)
        xip, xim = _calibrated(gg, kk)
        out.append(((i, j), Table({
            "theta": np.where(empty, gg.rnom, gg.meanr), "xip": xip, "xim": xim, "xip_raw": gg.xip,
            "xim_raw": gg.xim, "xip_im": gg.xip_im, "one_plus_k": one_plus_k,
            "sigma_xip": np.sqrt(gg.varxip) / one_plus_k, "sigma_xim": np.sqrt(gg.varxim) / one_plus_k,
            "npairs": gg.npairs, "weight": gg.weight})))
    jk = None
    if npatch:
        def vector(cs):
            return np.concatenate([np.concatenate(_calibrated(cs[2 * p], cs[2 * p + 1])) for p in range(len(pairs))])

        with np.errstate(invalid="ignore", divide="ignore"):
            jk = treecorr.estimate_multi_cov(corrs, "jackknife", func=vector, cross_patch_weight="match")
        sig = np.sqrt(np.diag(jk))
        for p, (_, t) in enumerate(out):
            t["sigma_xip_jk"] = sig[2 * nbins * p:2 * nbins * p + nbins]
            t["sigma_xim_jk"] = sig[2 * nbins * p + nbins:2 * nbins * (p + 1)]
    syscov = None
    if model is not None and n_sys > 0 and (model.kind == "binned" or model.grid is not None):
        syscov = _systematic_cov(model, tabs, pairs, corrs, cfg, n_sys, seed)
    return out, syscov, jk


def _systematic_cov(model, tabs, pairs, corrs, cfg, n_sys, seed):
    """Covariance of the data vector over (alpha, beta) draws of the calibration: 1 + K recomputed per draw.

    The draws' 1 + K are pair sums at TreeCorr's default bin_slop (fast), each multiplied by the ratio of the
    nominal 1 + K at the binning asked for (``cfg``) to the nominal at TreeCorr's default: the binning's
    effect on 1 + K, a smooth weighted mean of (1 + m_a)(1 + m_b), is the same for every draw.
    """
    fast = {k: v for k, v in cfg.items() if k not in ("bin_slop", "angle_slop")}
    exact_slop = cfg["bin_slop"] is not None and cfg["bin_slop"] < 0.1

    def one_plus_k(ms, kw):
        cats = [_catalog(t, 1.0 + np.where(np.isfinite(m), m, 0.0), with_shear=False) for t, m in zip(tabs, ms)]
        return [_process(treecorr.KKCorrelation(**kw), cats, i, j).xi for i, j in pairs]

    kw = fast if exact_slop else cfg
    if exact_slop:
        nominal = one_plus_k([model.m_of(t) for t in tabs], fast)
        ratio = [corrs[2 * p + 1].xi / np.where(nominal[p] != 0, nominal[p], np.nan) for p in range(len(pairs))]
    else:
        ratio = [1.0] * len(pairs)
    rng = np.random.default_rng(seed)
    vecs = []
    for draw in model.draws(n_sys, rng):
        ks = one_plus_k([draw.m_of(t) for t in tabs], kw)
        vec = []
        for p in range(len(pairs)):
            gg = corrs[2 * p]
            k2 = np.where(gg.npairs == 0, np.nan, ks[p] * ratio[p])
            vec += [gg.xip / k2, gg.xim / k2]
        vecs.append(np.concatenate(vec))
    return np.cov(np.array(vecs), rowvar=False)


def xipm(tab: Table, min_sep=1.0, max_sep=100.0, nbins=10, calibration=None, n_sys=100, seed=0,
         bin_slop=DEFAULT_BIN_SLOP, response=None, npatch=0, angle_slop=DEFAULT_ANGLE_SLOP):
    """xi+, xi- (raw and calibrated), 1 + K, errors and pair counts per bin; and the systematic covariance.

    The per-object m is the catalogue's ``m`` column unless a calibration
    file is given (then m(snr, scalelength) from its table or alpha, beta; a
    table of ``size: resolution`` takes the scalelength over the catalogue's
    ``psf_fwhm``). With a calibration file holding the likelihood grid, ``n_sys`` draws of
    (alpha, beta) give the systematic covariance of (xip, xim) concatenated.
    ``response`` (a metacal catalogue's ensemble response R, 2x2) replaces
    1 + m by the mean of R's diagonal for every galaxy, so that 1 + K = R^2.
    ``bin_slop``: TreeCorr's (default 0, exact pair binning; None for
    TreeCorr's own default). ``npatch`` >= 2 adds the jackknife errors
    (see :func:`xipm_bins`). Returns (table, covariance or None); with
    ``npatch``, (table, covariance or None, jackknife covariance).
    """
    if len(tab) < 2:
        raise ShearfitValueError(f"{len(tab)} measured galaxies: two-point functions need at least 2")
    out, syscov, jk = xipm_bins([tab], min_sep, max_sep, nbins, calibration=calibration, n_sys=n_sys, seed=seed,
                                bin_slop=bin_slop, responses=[response], npatch=npatch, angle_slop=angle_slop)
    table = out[0][1]
    return (table, syscov, jk) if npatch else (table, syscov)


def _cov_hdu(cov, name, pairs, nbins, comment, cards=()):
    from astropy.io import fits

    h = fits.ImageHDU(np.asarray(cov, float), name=name)
    h.header["NPAIRBIN"] = (len(pairs), "pairs of (tomographic) bins in the data vector")
    h.header["NTHETA"] = (nbins, "angular bins per xi")
    h.header["ORDER"] = ("PAIRk: xip, xim", "pair by pair: NTHETA xip, then NTHETA xim")
    for p, (i, j) in enumerate(pairs):
        h.header[f"PAIR{p}"] = (f"{i}_{j}", f"bins i_j of rows {2 * nbins * p}-{2 * nbins * (p + 1) - 1}")
    for key, val, c in cards:
        h.header[key] = (val, c)
    h.header["COMMENT"] = comment
    return h


def write_xipm_file(path, tables, names, table_cards, syscov=None, jkcov=None, pairs=((0, 0),), nbins=None,
                    cov_cards=(), primary_cards=()):
    """One FITS file: a table HDU per pair of bins (``names``, header cards ``table_cards`` of each), then
    ``SYSCOV`` (systematic covariance) and ``COV`` (jackknife covariance) if given, both over the data vector
    of :func:`xipm_bins`."""
    from astropy.io import fits

    from ..files import atomic_path

    nbins = nbins if nbins is not None else len(tables[0])
    hdus = [fits.PrimaryHDU()]
    for key, val, comment in primary_cards:
        hdus[0].header[key] = (val, comment)
    for table, name, cards in zip(tables, names, table_cards):
        h = fits.table_to_hdu(table)
        h.name = name
        for key, val, comment in cards:
            h.header[key] = (val, comment)
        hdus.append(h)
    if syscov is not None:
        hdus.append(_cov_hdu(syscov, "SYSCOV", pairs, nbins, "systematic covariance of (xip, xim) from the "
                             "calibration's (alpha, beta) likelihood"))
    if jkcov is not None:
        hdus.append(_cov_hdu(jkcov, "COV", pairs, nbins, "jackknife covariance of the calibrated (xip, xim) over "
                             "TreeCorr patches", cov_cards))
    with atomic_path(path) as tmp:
        fits.HDUList(hdus).writeto(tmp)


def write_xipm(table: Table, cov, path, header_cards=(), jkcov=None, cov_cards=()):
    """The xipm FITS file: HDU 1 the bins (docs/interface.rst), HDU SYSCOV the systematic covariance if any,
    HDU COV the jackknife covariance if any."""
    write_xipm_file(path, [table], ["XIPM"], [header_cards], syscov=cov, jkcov=jkcov, cov_cards=cov_cards)


def plot_xipm(results, path, labels=None, title=None):
    """theta * xi+ and theta * xi- against theta (log) with error bars, one panel per pair of bins.

    ``results``: ((i, j), table) as :func:`xipm_bins` returns; the errors are the jackknife ones where the
    tables have them, else the shape noise. Panels form the upper triangle of an nbin x nbin grid.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..files import atomic_path

    nb = 1 + max(j for (_, j), _ in results)
    fig, axes = plt.subplots(nb, nb, figsize=(3.6 * nb + 1, 3.0 * nb + 0.6), squeeze=False)
    for a in axes.ravel():
        a.set_visible(False)
    for (i, j), t in results:
        a = axes[i, j]
        a.set_visible(True)
        jk = "sigma_xip_jk" in t.colnames
        ok = np.asarray(t["npairs"]) > 0
        th = np.asarray(t["theta"])[ok]
        for col, fmt, lab, dx in (("xip", "o-", "xi+", 1.0), ("xim", "s--", "xi-", 1.03)):
            err = np.asarray(t[f"sigma_{col}_jk" if jk else f"sigma_{col}"])[ok]
            a.errorbar(th * dx, th * np.asarray(t[col])[ok], th * err, fmt=fmt, ms=3, lw=1, capsize=2, label=lab)
        a.axhline(0, color="k", lw=0.5)
        a.set_xscale("log")
        a.set_title(labels[(i, j)] if labels else f"bins {i}-{j}", fontsize=9)
        a.set_xlabel("theta (arcmin)")
        a.set_ylabel("theta x xi (arcmin)")
        a.tick_params(labelsize=8)
    axes[0, 0].legend(fontsize=8)
    errs = "jackknife" if "sigma_xip_jk" in results[0][1].colnames else "shape noise"
    fig.suptitle((title + "; " if title else "") + f"calibrated xi+, xi- (errors: {errs})", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
