"""Lensing weights that do not respond to shear.

lensfit's weight (sec. 3.5, :func:`shearfit.engine.sampling.lensing_weight`)
comes from each likelihood's own variance of e. For a galaxy whose likelihood
is broad, that variance depends on where the likelihood lies: a shear that
moves it towards ``|e| = 1`` squeezes it against the edge of the disc and the
posterior cut, its variance falls and its weight rises. Galaxies sheared along
their own ellipticity then weigh more than those sheared across it, and the
weighted mean over-responds to shear: a multiplicative bias that no per-object
ellipticity carries (measured on 0.1-0.2" galaxies at SNR 100-200 in
``benchmarks/README.md``, "Where lensfit's weight enters").

:func:`isotropic_weights` replaces each weight by the mean weight of the
galaxies like it, binned on quantities that a shear leaves unchanged to first
order: the signal-to-noise ratio and the circularised scalelength
``r sqrt(q)`` (a shear keeps the area; the semi-major axis ``r`` alone would
respond). Within a bin every orientation, and so every direction of the
shear relative to the galaxy, gets the same weight. What the weights still
do, down-weight the faint and the small, is kept at the resolution of the
bins.
"""

from __future__ import annotations

import numpy as np

from ..errors import FITCLASS_GALAXY, ShearfitValueError

__all__ = ["isotropic_weights", "circularised_scalelength"]


def circularised_scalelength(scalelength, e1, e2):
    """``r sqrt(q)`` with ``q = (1 - |e|) / (1 + |e|)``: the round scalelength of the same area."""
    e = np.hypot(np.asarray(e1, np.float64), np.asarray(e2, np.float64))
    with np.errstate(invalid="ignore"):
        return np.asarray(scalelength, np.float64) * np.sqrt((1 - e) / (1 + e))


def _quantile_bin(x, n):
    """Index of each value of ``x`` in ``n`` equal-number bins of ``x`` (fewer where values repeat)."""
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1))[1:-1])
    return np.searchsorted(edges, x, side="right")


def isotropic_weights(table, n_snr: int = 10, n_size: int = 10) -> np.ndarray:
    """Each galaxy's weight replaced by the mean weight of its bin of SNR and circularised scalelength.

    Parameters
    ----------
    table : astropy Table, structured array or mapping of arrays
        A catalogue with the columns ``weight``, ``snr``, ``scalelength``, ``e1``, ``e2`` and ``fitclass``
        (those of ``shearfit measure``).
    n_snr, n_size : int
        Equal-number bins in SNR and, within each SNR bin, in circularised scalelength (so every bin holds about
        ``N / (n_snr n_size)`` galaxies).

    Returns
    -------
    ndarray
        One weight per row: the bin's mean of ``weight`` over its galaxies (``fitclass == 0`` with finite
        ``e1``, ``e2``, ``snr`` and ``scalelength``), and 0 for every other row. A galaxy whose own weight is 0
        (a likelihood as broad as the prior) counts as 0 in its bin's mean and gets that mean too: whether a
        likelihood is that broad also depends on the shear. Each bin's sum of weights is kept.
    """
    if int(n_snr) < 1 or int(n_size) < 1:
        raise ShearfitValueError(f"isotropic_weights: n_snr and n_size must be >= 1, got {n_snr}, {n_size}")
    cols = {}
    for c in ("weight", "snr", "scalelength", "e1", "e2", "fitclass"):
        try:
            cols[c] = np.asarray(table[c])
        except (KeyError, ValueError):
            raise ShearfitValueError(f"isotropic_weights: the catalogue has no column '{c}'") from None
    w = np.asarray(cols["weight"], np.float64)
    snr = np.asarray(cols["snr"], np.float64)
    size = circularised_scalelength(cols["scalelength"], cols["e1"], cols["e2"])
    good = ((cols["fitclass"] == FITCLASS_GALAXY) & np.isfinite(w) & np.isfinite(snr) & np.isfinite(size)
            & np.isfinite(np.asarray(cols["e1"], np.float64)) & np.isfinite(np.asarray(cols["e2"], np.float64)))
    out = np.zeros(w.shape)
    if not np.any(good):
        return out
    idx = np.flatnonzero(good)
    i = _quantile_bin(snr[idx], int(n_snr))
    j = np.zeros_like(i)
    for k in np.unique(i):
        s = i == k
        j[s] = _quantile_bin(size[idx][s], int(n_size))
    key = i * int(n_size) + j
    n_bins = int(n_snr) * int(n_size)
    total = np.bincount(key, w[idx], n_bins)
    count = np.bincount(key, None, n_bins)
    out[idx] = (total / np.maximum(count, 1))[key]
    return out
