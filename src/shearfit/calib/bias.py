"""Shear-bias statistics of ring tests with +g / -g noise cancellation.

A ring test simulates every galaxy at ``n_rotations`` orientations (intrinsic
ellipticity rotated by ``2 pi j / n_rotations``), once with shear ``+g`` and
once with ``-g``, the two runs sharing galaxy, PSFs, dithers *and noise*
(:func:`shearfit.simulate.ring_set` with equal generator states). With the
linear model ``<e> = (1 + m) g + c`` per component,

.. math::

    m_i = \\frac{\\langle e_i \\rangle_+ - \\langle e_i \\rangle_-}{2 g_i} - 1, \\qquad
    c_i = \\frac{\\langle e_i \\rangle_+ + \\langle e_i \\rangle_-}{2},

where ``<>`` is the (lensfit-)weighted mean over all objects of one sign. The
rotations cancel the shape noise and the shared noise cancels most of the
pixel noise in the difference, so a few dozen galaxies already give a useful
m. Errors come from a bootstrap over *galaxies*: a galaxy carries its whole
ring at both signs, which keeps the correlations that the cancellation relies
on.

Everything works on per-galaxy sums (:func:`ring_sums`), so that a bootstrap
resampling is a weighted sum over galaxies and thousands of resamplings cost
one matrix product.

This module is the one home of shear-bias estimates with bootstrap errors: ring
tests (``benchmarks/ring_test.py``), the demos (:mod:`shearfit.app.demo`,
:mod:`shearfit.app.demo_stamps`) and the calibration's binned fits
(:mod:`shearfit.calib.calibrate`, through :func:`group_resamples`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import ShearfitValueError

__all__ = [
    "ring_sums",
    "paired_weights",
    "bias_from_sums",
    "mean_shear_from_sums",
    "bootstrap_counts",
    "group_resamples",
    "shear_bias",
    "mean_shear",
    "shear_bias_by_snr",
    "snr_bin_masks",
    "galaxy_column",
    "metacal_ring_sums",
    "metacal_bias_from_sums",
    "METACAL_SUM_NAMES",
    "METACAL_BIAS_NAMES",
    "format_with_error",
    "BIAS_NAMES",
]

#: Order of the entries of every bias vector this module returns.
BIAS_NAMES = ("m1", "m2", "c1", "c2")

#: ``fitclass`` of the objects that enter the means (galaxies; see :mod:`shearfit.errors`).
_GALAXY = 0


def _galaxy_sign_sums(table, n_galaxies, columns) -> np.ndarray:
    """Each column of per-object values summed per galaxy and sign: (len(columns), n_galaxies, 2), sign 0 for
    ``+g`` and 1 for ``-g``, after checking the table's ``galaxy`` column."""
    galaxy = np.asarray(table["galaxy"])
    if galaxy.size and (not np.issubdtype(galaxy.dtype, np.integer) or galaxy.min() < 0
                        or galaxy.max() >= n_galaxies):
        raise ShearfitValueError(f"column 'galaxy' must hold integers in [0, {n_galaxies})")
    sign = (np.asarray(table["sign"]) < 0).astype(np.intp)
    sums = np.zeros((len(columns), n_galaxies, 2))
    for k, v in enumerate(columns):
        np.add.at(sums[k], (galaxy, sign), v)
    return sums


def ring_sums(table, n_galaxies: int, weighted: bool = True) -> np.ndarray:
    """Per-galaxy sums of ``w``, ``w e1`` and ``w e2`` for each sign of the shear.

    Only objects with ``fitclass == 0`` (galaxies) and finite ``e1``, ``e2``
    enter; any other object (star, failure, NaN) counts with weight zero, as it
    would in a catalogue.

    Parameters
    ----------
    table : structured array, astropy Table or mapping of arrays
        One row per measured object, with columns ``galaxy`` (integer index in
        ``[0, n_galaxies)``), ``sign`` (+1 or -1: the sign of the applied
        shear), ``fitclass``, ``e1``, ``e2`` and, if ``weighted``, ``weight``.
    n_galaxies : int
        Number of galaxies (a galaxy whose objects all failed still counts: it
        is drawn, with zero weight, by the bootstrap).
    weighted : bool
        Use the ``weight`` column (lensfit's weight); otherwise every
        ``fitclass == 0`` object has unit weight. Non-finite weights count as
        zero.

    Returns
    -------
    ndarray of shape (3, n_galaxies, 2)
        ``sums[k, i, s]``: ``k`` = 0, 1, 2 for ``w``, ``w e1``, ``w e2``; ``i``
        the galaxy; ``s`` = 0 for the ``+g`` objects, 1 for ``-g``.
    """
    e1 = np.asarray(table["e1"], dtype=np.float64)
    e2 = np.asarray(table["e2"], dtype=np.float64)
    good = (np.asarray(table["fitclass"]) == _GALAXY) & np.isfinite(e1) & np.isfinite(e2)
    if weighted:
        w = np.asarray(table["weight"], dtype=np.float64)
        w = np.where(good & np.isfinite(w), w, 0.0)
    else:
        w = good.astype(np.float64)
    e1 = np.where(good, e1, 0.0)
    e2 = np.where(good, e2, 0.0)
    return _galaxy_sign_sums(table, int(n_galaxies), (w, w * e1, w * e2))


def paired_weights(table) -> np.ndarray:
    """Each object's weight replaced by the mean over its pair: the same galaxy and orientation (``galaxy`` and
    ``rotation`` columns) at ``+g`` and at ``-g``, drawn with the same noise.

    The weights then do not respond to the shear, while each keeps its dependence on the galaxy, its
    orientation and its noise: m with the weights as measured less m with these is the part of m that comes
    from the weights' response to shear (a weight that grows as a shear makes a galaxy more elliptical makes
    the weighted mean over-respond). Where a pair's other member is not counted by :func:`ring_sums` (not a
    galaxy, ``fitclass != 0``, or no finite ellipticity) the object keeps its own weight; those not counted get 0.

    Returns
    -------
    ndarray
        One weight per row of ``table``.
    """
    # the objects ring_sums counts: galaxies with finite ellipticities
    good = ((np.asarray(table["fitclass"]) == _GALAXY) & np.isfinite(np.asarray(table["e1"], dtype=np.float64))
            & np.isfinite(np.asarray(table["e2"], dtype=np.float64)))
    w = np.where(good, np.nan_to_num(np.asarray(table["weight"], dtype=np.float64)), 0.0)
    sign = np.asarray(table["sign"])
    key = np.stack([np.asarray(table["galaxy"], np.int64), np.asarray(table["rotation"], np.int64)], axis=1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = int(inv.max()) + 1 if inv.size else 0
    members = np.bincount(inv, minlength=n)
    signs = np.bincount(inv, sign > 0, minlength=n)
    if np.any((members > 2) | ((members == 2) & (signs != 1))):
        raise ShearfitValueError("paired_weights: a (galaxy, rotation) pair must hold one +g and one -g object")
    both = (np.bincount(inv, good, minlength=n) == 2)[inv]
    mean = (np.bincount(inv, w, minlength=n) / 2.0)[inv]
    return np.where(both, mean, w)


def mean_shear_from_sums(sums, counts=None) -> np.ndarray:
    """Weighted mean ellipticity of each sign, optionally for resampled galaxies.

    Parameters
    ----------
    sums : ndarray of shape (3, n_galaxies, 2)
        From :func:`ring_sums`.
    counts : ndarray of shape (..., n_galaxies), optional
        Multiplicity of each galaxy (a bootstrap resampling); default one each.

    Returns
    -------
    ndarray of shape (..., 2, 2)
        ``[..., s, i]``: the mean of ``e_(i+1)`` over the objects of sign ``s``
        (0: ``+g``, 1: ``-g``); NaN where the total weight is zero.
    """
    sums = np.asarray(sums, dtype=np.float64)
    if sums.ndim != 3 or sums.shape[0] != 3 or sums.shape[2] != 2:
        raise ShearfitValueError(f"sums must have shape (3, n_galaxies, 2), got {sums.shape}")
    if counts is None:
        counts = np.ones(sums.shape[1])
    S = np.einsum("...g,kgs->...sk", np.asarray(counts, dtype=np.float64), sums)  # (..., 2 signs, 3)
    w = S[..., :1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w != 0, S[..., 1:] / np.where(w != 0, w, 1.0), np.nan)


def bias_from_sums(sums, g, counts=None) -> np.ndarray:
    """m1, m2, c1, c2 of per-galaxy ring sums, optionally for resampled galaxies.

    Parameters
    ----------
    sums : ndarray of shape (3, n_galaxies, 2)
        From :func:`ring_sums`.
    g : (g1, g2)
        The applied shear of the ``+g`` set (the ``-g`` set has ``-g``). A
        zero component gives a NaN m for that component.
    counts : ndarray of shape (..., n_galaxies), optional
        Multiplicity of each galaxy; default one each.

    Returns
    -------
    ndarray of shape (..., 4)
        m1, m2, c1, c2 (see :data:`BIAS_NAMES`).
    """
    g = np.asarray(g, dtype=np.float64).reshape(2)
    mean_e = mean_shear_from_sums(sums, counts)
    plus, minus = mean_e[..., 0, :], mean_e[..., 1, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        m = (plus - minus) / (2.0 * np.where(g != 0, g, np.nan)) - 1.0
    c = 0.5 * (plus + minus)
    return np.concatenate([m, c], axis=-1)


def bootstrap_counts(n_galaxies: int, n_boot: int, rng) -> np.ndarray:
    """Multiplicities of ``n_boot`` bootstrap resamplings of ``n_galaxies`` galaxies.

    Parameters
    ----------
    n_galaxies, n_boot : int
    rng : numpy.random.Generator or seed

    Returns
    -------
    ndarray of shape (n_boot, n_galaxies)
        Each row sums to ``n_galaxies``.
    """
    rng = np.random.default_rng(rng)
    idx = rng.integers(0, n_galaxies, size=(n_boot, n_galaxies))
    counts = np.zeros((n_boot, n_galaxies))
    np.add.at(counts, (np.arange(n_boot)[:, None], idx), 1.0)
    return counts


def group_resamples(rows, groups, n_boot: int, rng) -> list:
    """Bootstrap resamplings of ``rows`` that draw whole groups, as index arrays.

    Parameters
    ----------
    rows : ndarray of int
        The rows to resample.
    groups : ndarray
        A group label per row of the whole table (``groups[rows]`` are the
        rows' labels): rows that share noise or a galaxy are drawn together.
    n_boot : int
    rng : numpy.random.Generator

    Returns
    -------
    list of ndarray
        ``n_boot`` arrays of row indices; with one row per group, the plain
        bootstrap of the rows.
    """
    codes, inv = np.unique(groups[rows], return_inverse=True)
    if codes.size == rows.size:                      # one row per group: the plain bootstrap
        return [rng.choice(rows, rows.size) for _ in range(n_boot)]
    order = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[order], np.arange(codes.size + 1))
    members = [rows[order[starts[k]:starts[k + 1]]] for k in range(codes.size)]
    return [np.concatenate([members[k] for k in rng.integers(0, codes.size, codes.size)]) for _ in range(n_boot)]


def _boot_std(boot):
    """Standard deviation over axis 0 ignoring NaN, NaN where fewer than two values are finite."""
    boot = np.asarray(boot, dtype=np.float64)
    n = np.isfinite(boot).sum(axis=0)
    out = np.full(boot.shape[1:], np.nan)
    ok = n >= 2
    if np.any(ok):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out[ok] = np.nanstd(boot[:, ok], axis=0, ddof=1)
    return out


def shear_bias(sums, g, n_boot: int = 200, rng=None):
    """Multiplicative and additive shear bias with bootstrap errors.

    Parameters
    ----------
    sums : ndarray of shape (3, n_galaxies, 2)
        From :func:`ring_sums`.
    g : (g1, g2)
        Shear applied to the ``+g`` set.
    n_boot : int
        Bootstrap resamplings of whole galaxies (each with its ring at both
        signs).
    rng : numpy.random.Generator or seed, optional

    Returns
    -------
    estimate : ndarray of shape (4,)
        m1, m2, c1, c2 from all galaxies.
    errors : ndarray of shape (4,)
        Their bootstrap standard deviations; NaN with fewer than two galaxies
        or bootstrap resamplings.
    """
    sums = np.asarray(sums, dtype=np.float64)
    n_gal = sums.shape[1] if sums.ndim == 3 else 0
    est = bias_from_sums(sums, g)
    if n_gal < 2 or n_boot < 2:
        return est, np.full(4, np.nan)
    boot = bias_from_sums(sums, g, bootstrap_counts(n_gal, int(n_boot), rng))
    return est, _boot_std(boot)


def mean_shear(sums, n_boot: int = 200, rng=None):
    """Weighted mean ellipticity of the ``+g`` and ``-g`` sets with bootstrap errors.

    In a ring test the mean ellipticity estimates the applied shear,
    ``(1 + m) g + c``.

    Parameters
    ----------
    sums : ndarray of shape (3, n_galaxies, 2)
        From :func:`ring_sums`.
    n_boot : int
    rng : numpy.random.Generator or seed, optional

    Returns
    -------
    estimate : ndarray of shape (2, 2)
        ``[s, i]``: mean ``e_(i+1)`` of sign ``s`` (0: ``+g``, 1: ``-g``).
    errors : ndarray of shape (2, 2)
        Bootstrap standard deviations over galaxies (NaN with fewer than two).
    """
    sums = np.asarray(sums, dtype=np.float64)
    est = mean_shear_from_sums(sums)
    n_gal = sums.shape[1]
    if n_gal < 2 or n_boot < 2:
        return est, np.full((2, 2), np.nan)
    boot = mean_shear_from_sums(sums, bootstrap_counts(n_gal, int(n_boot), rng))
    return est, _boot_std(boot)


#: The sums of :func:`metacal_ring_sums`, in order: the noshear fit's weight and weighted e, its weight where R is
#: finite and the weighted R, then each sheared version's weight and the noshear e under that weight.
METACAL_SUM_NAMES = (("w", "w e1", "w e2", "w_R", "w R11", "w R12", "w R21", "w R22")
                     + tuple(f"{q}_{v}" for v in ("1p", "1m", "2p", "2m") for q in ("w", "w e1", "w e2")))

#: Order of the entries of :func:`metacal_bias_from_sums`'s bias vector: m and c with the whole <R>, m of lensfit's
#: e without the response, m with the diagonal of <R> only, and m with the mean of its diagonal for both components.
METACAL_BIAS_NAMES = ("m1", "m2", "c1", "c2", "raw_m1", "raw_m2", "diag_m1", "diag_m2", "scalar_m1", "scalar_m2")


def metacal_ring_sums(table, n_galaxies: int, weighted: bool = True, select: bool = True) -> np.ndarray:
    """Per-galaxy sums of a metacal ring table, for each sign of the shear: what its m and c are made of.

    The ensemble shear of a metacal catalogue, ``<R>^-1 <e>`` with ``<R> = <R_gamma> + R_S``
    (:func:`shearfit.calib.metacal.ensemble_response`), is a function of weighted sums over its objects; summed
    per galaxy and sign, a bootstrap over galaxies is a matrix product, and a long run's result can be kept in a
    few hundred bytes per galaxy.

    Parameters
    ----------
    table : structured array, astropy Table or mapping of arrays
        One row per object with ``galaxy``, ``sign``, ``e1``, ``e2``, ``weight``, ``fitclass``, ``R11`` ..
        ``R22`` and, for each sheared version ``v`` of ``1p, 1m, 2p, 2m``, ``weight_v`` and ``fitclass_v``.
    n_galaxies : int
    weighted : bool
        Lensfit's weights; otherwise each version's galaxies (``fitclass == 0``) weigh one.
    select : bool
        False: no selection at all, for simulations without stars: every object whose noshear e and R are finite
        weighs one in every version, whatever its ``fitclass`` (``weighted`` is then ignored). The selection
        response is then zero by construction, and the m that remains is that of the shear response alone.

    Returns
    -------
    ndarray of shape (20, n_galaxies, 2)
        ``sums[k, i, s]``, ``k`` as :data:`METACAL_SUM_NAMES`; ``s`` = 0 for ``+g``, 1 for ``-g``.
    """
    n = len(np.asarray(table["galaxy"]))
    R = [np.asarray(table[f"R{i}{j}"], dtype=np.float64) for i in (1, 2) for j in (1, 2)]
    finite_R = np.all(np.isfinite(R), axis=0)
    measured = (finite_R & np.isfinite(np.asarray(table["e1"], dtype=np.float64))
                & np.isfinite(np.asarray(table["e2"], dtype=np.float64)))

    def weight(sfx):
        if not select:
            return measured.astype(np.float64)
        ok = np.asarray(table[f"fitclass{sfx}"]) == _GALAXY
        w = np.asarray(table[f"weight{sfx}"], dtype=np.float64) if weighted else np.ones(n)
        return np.where(ok & np.isfinite(w), w, 0.0)

    e = [np.nan_to_num(np.asarray(table[c], dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0) for c in ("e1", "e2")]
    w0 = weight("")
    wR = np.where(finite_R, w0, 0.0)
    cols = [w0, w0 * e[0], w0 * e[1], wR] + [wR * np.where(wR > 0, r, 0.0) for r in R]
    for v in ("1p", "1m", "2p", "2m"):
        wv = weight(f"_{v}")
        cols += [wv, wv * e[0], wv * e[1]]
    return _galaxy_sign_sums(table, int(n_galaxies), cols)


def metacal_bias_from_sums(sums, g, counts=None, delta: float = 0.01):
    """Metacal m and c of per-galaxy sums (:func:`metacal_ring_sums`), optionally for resampled galaxies.

    Parameters
    ----------
    sums : ndarray of shape (20, n_galaxies, 2)
    g : (g1, g2)
        The applied shear of the ``+g`` objects.
    counts : ndarray of shape (..., n_galaxies), optional
        Multiplicity of each galaxy (:func:`bootstrap_counts`); default one each.
    delta : float
        Metacal's shear step (the selection response differences the versions over ``+-delta``).

    Returns
    -------
    bias : ndarray of shape (..., 10)
        As :data:`METACAL_BIAS_NAMES`.
    R_gamma, R_S : ndarray of shape (..., 2, 2)
        The shear and selection responses, averaged over the two signs.
    """
    sums = np.asarray(sums, dtype=np.float64)
    if sums.ndim != 3 or sums.shape[0] != len(METACAL_SUM_NAMES) or sums.shape[2] != 2:
        raise ShearfitValueError(f"sums must have shape ({len(METACAL_SUM_NAMES)}, n_galaxies, 2), got {sums.shape}")
    g = np.asarray(g, dtype=np.float64).reshape(2)
    if counts is None:
        counts = np.ones(sums.shape[1])
    S = np.einsum("...g,kgs->...sk", np.asarray(counts, dtype=np.float64), sums)   # (..., 2 signs, 20)
    with np.errstate(invalid="ignore", divide="ignore"):
        ebar = S[..., 1:3] / S[..., 0:1]
        R_gamma = (S[..., 4:8] / S[..., 3:4]).reshape(S.shape[:-1] + (2, 2))
        R_S = np.zeros_like(R_gamma)
        for j in range(2):
            p, m = 8 + 6 * j, 11 + 6 * j
            R_S[..., :, j] = (S[..., p + 1:p + 3] / S[..., p:p + 1] - S[..., m + 1:m + 3] / S[..., m:m + 1]) / (2 * delta)
        R = R_gamma + R_S
        det = R[..., 0, 0] * R[..., 1, 1] - R[..., 0, 1] * R[..., 1, 0]
        shear = np.stack([R[..., 1, 1] * ebar[..., 0] - R[..., 0, 1] * ebar[..., 1],
                          R[..., 0, 0] * ebar[..., 1] - R[..., 1, 0] * ebar[..., 0]], axis=-1) / det[..., None]
        diag = ebar / np.stack([R[..., 0, 0], R[..., 1, 1]], axis=-1)
        scalar = ebar / ((R[..., 0, 0] + R[..., 1, 1]) / 2)[..., None]

        def m_of(x):
            return (x[..., 0, :] - x[..., 1, :]) / (2 * np.where(g != 0, g, np.nan)) - 1

        bias = np.concatenate([m_of(shear), (shear[..., 0, :] + shear[..., 1, :]) / 2, m_of(ebar), m_of(diag),
                               m_of(scalar)], axis=-1)
    return bias, R_gamma.mean(axis=-3), R_S.mean(axis=-3)


def galaxy_column(table, column: str, n_galaxies: int) -> np.ndarray:
    """One value per galaxy of a column that is constant over a galaxy's objects.

    Parameters
    ----------
    table : structured array, astropy Table or mapping of arrays
        With a ``galaxy`` column.
    column : str
        E.g. ``"snr_target"`` or ``"mag"``.
    n_galaxies : int

    Returns
    -------
    ndarray of shape (n_galaxies,)
        NaN for a galaxy with no row.
    """
    out = np.full(int(n_galaxies), np.nan)
    out[np.asarray(table["galaxy"])] = np.asarray(table[column], dtype=np.float64)
    return out


def snr_bin_masks(snr, edges):
    """(lo, hi, mask) of each bin of ``edges`` over the values ``snr``: lo <= snr < hi, the last bin including
    its upper edge."""
    snr = np.asarray(snr, dtype=np.float64)
    n_bins = len(edges) - 1
    return [(float(lo), float(hi), (snr >= lo) & ((snr <= hi) if k == n_bins - 1 else (snr < hi)))
            for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:]))]


def shear_bias_by_snr(sums, galaxy_snr, edges, g, n_boot: int = 200, rng=None) -> list:
    """m and c in bins of a per-galaxy SNR: the noise-bias signature.

    Parameters
    ----------
    sums : ndarray of shape (3, n_galaxies, 2)
        From :func:`ring_sums`.
    galaxy_snr : ndarray of shape (n_galaxies,)
        The SNR that bins the galaxies (e.g. the target SNR of the
        simulation, :func:`galaxy_column`).
    edges : sequence of float
        Bin edges, increasing; the last bin includes its upper edge.
    g : (g1, g2)
    n_boot : int
    rng : numpy.random.Generator or seed, optional
        One generator for all bins (resamplings differ between bins).

    Returns
    -------
    list of dict
        One per bin, with ``lo``, ``hi``, ``n_galaxies``, ``galaxies`` (their
        indices), ``estimate`` and ``errors`` (as :func:`shear_bias`; NaN
        for a bin of fewer than two galaxies).
    """
    sums = np.asarray(sums, dtype=np.float64)
    snr = np.asarray(galaxy_snr, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    if snr.shape != (sums.shape[1],):
        raise ShearfitValueError(f"galaxy_snr needs one value per galaxy ({sums.shape[1]}), got shape {snr.shape}")
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ShearfitValueError("edges must be an increasing sequence of at least two values")
    rng = np.random.default_rng(rng)
    out = []
    for lo, hi, sel in snr_bin_masks(snr, edges):
        n = int(sel.sum())
        if n >= 2:
            est, err = shear_bias(sums[:, sel], g, n_boot, rng)
        else:
            est, err = np.full(4, np.nan), np.full(4, np.nan)
        out.append({"lo": float(lo), "hi": float(hi), "n_galaxies": n, "galaxies": np.flatnonzero(sel),
                    "estimate": est, "errors": err})
    return out


def format_with_error(value: float, error: float, scale: float = 1.0, digits: int = 5) -> str:
    """``"+0.01234 +/- 0.00456"`` with fixed widths for tables; ``"nan"`` for a non-finite value.

    Parameters
    ----------
    value, error : float
    scale : float
        Multiplies both (e.g. 1e3 to print in units of 1e-3).
    digits : int
        Decimals.
    """
    value, error = float(value), float(error)
    width = digits + 4
    if not math.isfinite(value):
        return f"{'nan':>{width}s}"
    err = f"{error * scale:{width - 1}.{digits}f}" if math.isfinite(error) else f"{'nan':>{width - 1}s}"
    return f"{value * scale:+{width}.{digits}f} +/- {err}"
