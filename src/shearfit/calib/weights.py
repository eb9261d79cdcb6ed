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
galaxies like it, binned on a quantity that does not depend on the galaxy's
shape, so that a shear leaves it unchanged: ``flux_snr``, the SNR of the
fitted flux were the object a point source (measured on rings of 0.1-0.125"
galaxies, d ln flux_snr / dg = -0.0001 e without noise and +0.003 e with it,
e the intrinsic ellipticity along the shear). Within a bin every orientation, and so
every direction of the shear relative to the galaxy, gets the same weight.
What the weights still do, down-weight the faint, is kept at the resolution of
the bins.

A second axis of size (``n_size`` > 1) bins on ``round_scalelength``, the
likelihood mean of the round scalelength of each sample's area, ``r sqrt(q)``;
it is off by default because no size a fit measures is quite invariant. On
noise-free 0.1-0.125" galaxies (200 rings, ``benchmarks/README.md``, session
57), against weights that do not respond at all, m moved by -0.0003 +- 0.0003
with bins of ``flux_snr`` alone, by -0.0037 +- 0.0019 / -0.0077 +- 0.0024 with
10 x 10 bins of ``flux_snr`` and ``round_scalelength`` (-0.0024 +- 0.0009 /
-0.0027 +- 0.0007 with the bins' mean weights interpolated in size; its own
response: d ln r / dg = +0.065 e, with a scatter of 0.15 from galaxy to
galaxy), and by -0.0043 +- 0.0020 / -0.0033 +- 0.0018 with the catalogue's
``snr`` and the circularised scalelength of the estimate (``snr`` falls as a
shear spreads the light: -0.18 e; the semi-major axis ``scalelength``
responds as +2.3 e).
"""

from __future__ import annotations

import numpy as np

from ..errors import FITCLASS_GALAXY, ShearfitValueError

__all__ = ["isotropic_weights", "circularised_scalelength", "isotropic_bins"]

#: galaxies per bin that :func:`isotropic_bins` aims at: each bin's mean weight then carries no single galaxy's
#: response to shear (one galaxy is at most 1 % of its bin)
MIN_PER_BIN = 100


def circularised_scalelength(scalelength, e1, e2):
    """``r sqrt(q)`` with ``q = (1 - |e|) / (1 + |e|)``: the round scalelength of the same area as an ellipse of
    semi-major axis ``r`` and ellipticity ``e`` (for a catalogue's estimates, not its ``round_scalelength``: the
    mean of a broad likelihood is rounder than its samples)."""
    e = np.hypot(np.asarray(e1, np.float64), np.asarray(e2, np.float64))
    with np.errstate(invalid="ignore"):
        return np.asarray(scalelength, np.float64) * np.sqrt((1 - e) / (1 + e))


def isotropic_bins(n_galaxies: int, max_bins: int = 10, min_per_bin: int = MIN_PER_BIN) -> int:
    """The bins of ``flux_snr`` for :func:`isotropic_weights` on ``n_galaxies``: at most ``max_bins``, and at
    least ``min_per_bin`` galaxies in each (1 for a catalogue of fewer than ``2 min_per_bin``: one mean weight
    for all)."""
    n = max(int(n_galaxies), 0) // int(min_per_bin)
    return int(min(max(n, 1), int(max_bins)))


def _quantile_bin(x, n):
    """Index of each value of ``x`` in ``n`` equal-number bins of ``x`` (fewer where values repeat)."""
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1))[1:-1])
    return np.searchsorted(edges, x, side="right")


def isotropic_weights(table, n_snr: int = 10, n_size: int = 1) -> np.ndarray:
    """Each galaxy's weight replaced by the mean weight of its bin of ``flux_snr`` (and of ``round_scalelength``).

    Parameters
    ----------
    table : astropy Table, structured array or mapping of arrays
        A catalogue with the columns ``weight``, ``flux_snr``, ``round_scalelength``, ``e1``, ``e2`` and
        ``fitclass`` (those of ``shearfit measure``).
    n_snr, n_size : int
        Equal-number bins in ``flux_snr`` and, within each of them, in ``round_scalelength`` (so every bin holds
        about ``N / (n_snr n_size)`` galaxies; :func:`isotropic_bins` chooses ``n_snr`` for a catalogue). The
        default ``n_size = 1`` leaves the size out (see the module's text).

    Returns
    -------
    ndarray
        One weight per row: the bin's mean of ``weight`` over its galaxies (``fitclass == 0`` with finite
        ``e1``, ``e2``, ``flux_snr`` and ``round_scalelength``), and 0 for every other row. A galaxy whose own
        weight is 0 (a likelihood as broad as the prior) counts as 0 in its bin's mean and gets that mean too:
        whether a likelihood is that broad also depends on the shear. Each bin's sum of weights is kept.
    """
    if int(n_snr) < 1 or int(n_size) < 1:
        raise ShearfitValueError(f"isotropic_weights: n_snr and n_size must be >= 1, got {n_snr}, {n_size}")
    cols = {}
    for c in ("weight", "flux_snr", "round_scalelength", "e1", "e2", "fitclass"):
        try:
            cols[c] = np.asarray(table[c])
        except (KeyError, ValueError):
            raise ShearfitValueError(f"isotropic_weights: the catalogue has no column '{c}'") from None
    w = np.asarray(cols["weight"], np.float64)
    snr = np.asarray(cols["flux_snr"], np.float64)
    size = np.asarray(cols["round_scalelength"], np.float64)
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
