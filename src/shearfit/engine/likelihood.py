"""The joint likelihood over exposures and its marginalisation (sec. 3.2, 4).

For a model (e1, e2, r) the pixel sums that the likelihood needs are, with
f the disk and g the bulge component of unit flux (PSF-convolved, pixelised,
on every exposure) and y the data::

    ff = sum f^2/s^2,  gg = sum g^2/s^2,  fg = sum f g/s^2    (position-free)
    h_f(x) = sum f(.-x) y/s^2,  h_g(x) = sum g(.-x) y/s^2    (cross-correlations)

summed over all pixels of all exposures. Each is a sum over Fourier modes of
the profile transform R(rho_j) times a per-mode weight that depends only on
the data, so a batch of models costs one profile evaluation per mode and a
few matrix products. The cross-correlations of all exposures add in Fourier
space around one common celestial position; the position peak is found once
per object (for centrally symmetric models it does not depend on the model's
shape, see ``find_position``), and each model's own small offset from it is
taken into account to second order through the gradient and Hessian of h.

Then (sec. 3.2): the bulge fraction is marginalised analytically (erf), the
position by a 2D Gaussian on the pedestal integrated to r_max (exponential
integral), the flux numerically with the S^-alpha prior (cubic spline).
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy import fft as sfft
from scipy import sparse, special
from scipy.interpolate import CubicSpline

from ..config import FitConfig
from ..errors import ShearfitValueError
from .kernel import KERNEL, USE_KERNEL, special_capsules
from .model import ExposureModes, complex_bincount, indices_by_shape, inv2, shape_matrix


__all__ = ["JointModes", "join_exposures", "model_sums", "ModelSums", "flux_position_marginal",
           "log_erf_diff", "log_ei_minus", "find_position"]

LOG_2PI = np.log(2 * np.pi)


@dataclass
class JointModes:
    """All exposures' Fourier modes of one object, merged where they coincide.

    A mode is a sky wavevector K. Exposures whose Jacobians are equal sample
    the same K (dithers only change phases), so their modes are merged into
    one: the model's transform is evaluated once per K for all of them.
    The likelihood's sums are then, for the transform R(K) of a model::

        h = sum_K R(K) Re(z(K) ...),  ff = sum_K q(K) R(K)^2 + R_m^T Re(H) R_m

    where z adds the exposures' cross-correlation weights at K, q their
    Parseval weights for modes alone on their sampled mode, and H (over the
    modes ``multi``, whose sampled modes also hold alias images above
    Nyquist, sec. 6 / App. A) is ``F^H F`` for F the matrix taking the
    transforms at those K to every exposure's sampled modes: block diagonal,
    one block of ``msizes[g]`` modes per group of modes linked by a fold.
    """

    kx: np.ndarray
    ky: np.ndarray
    z: np.ndarray          # sum over exposures of conj(Y_c) T w_c / (N sigma^2): cross-correlation weight
    q: np.ndarray          # sum over exposures of w_c |T|^2 / (N sigma^2) for modes in no fold group, else 0
    multi: np.ndarray      # the modes in fold groups, group after group
    msizes: np.ndarray     # the number of modes of each group (summing to multi.size)
    H: object              # sparse complex Hermitian (multi.size x multi.size), F^H F, block diagonal
    basis: np.ndarray      # (3, n) [kx^2, 2 kx ky, ky^2]
    yy: float
    npix: int
    n_exposures: int
    pixel_scale: float
    keep: list = None      # per exposure, the modes the noise-aware cut kept (None: all)
    decoupled: np.ndarray = None   # per fold group found, whether its cross terms were dropped (None: none)
    # a model's fold-group cross terms are left out of its binned sums where their bound from the model's own
    # transform at their bins (binned_sums) is within this: pair_tolerance / S^2 (join_exposures); 0: never
    pair_skip: float = 0.0
    data_map: object = field(default=None, repr=False)   # how z was made from the exposures' data (_DataMap)

    @property
    def n_modes(self):
        return self.kx.size

    def with_data(self, exposures):
        """The same modes with z and yy from other data on the same exposures (another version of the
        object's stamps with the same PSFs, Jacobians, offsets and noise: metacal's); None where the
        exposures do not match those these modes were made from."""
        dm = self.data_map
        if dm is None or len(exposures) != len(dm.sigma2) or any(
                ex.sigma2 != s or ex.data_ft is None or ex.data_ft.size != n
                for ex, s, n in zip(exposures, dm.sigma2, dm.sizes)):
            return None
        out = replace(self, z=dm.merged_z(exposures) * dm.phase, yy=float(sum(ex.yy for ex in exposures)),
                      npix=int(sum(ex.npix for ex in exposures)))
        # what depends on the modes alone, not on the data, is shared (the binning's geometry made first, so
        # that the versions bin together: mode_bins_versions)
        _bins_geometry(self)
        for name in ("_factors", "_bins32_geometry"):
            cached = getattr(self, name, None)
            if cached is not None:
                setattr(out, name, cached)
        return out

    def group_factors(self):
        """(ranks, factors) of the fold groups' blocks of Re H (``_block_factors``), cached."""
        cache = getattr(self, "_factors", None)
        if cache is None:
            ranks, factors = _block_factors(sparse.csr_matrix(self.H.real), self.msizes)
            cache = self._factors = (ranks, np.ascontiguousarray(factors, dtype=float))
        return cache

    def single_modes(self):
        """The modes in no fold group (alone on their sampled mode), in order."""
        single = np.ones(self.n_modes, bool)
        single[self.multi] = False
        return np.nonzero(single)[0]

    def packed(self):
        """The modes interleaved for the kernel (cached): (rows, n_single, group sizes, group weights).

        Rows are 12 doubles, [kx^2, 2 kx ky, ky^2, lin0..lin5, q, 0, 0]: the modes in no group first,
        then those of ``multi`` in its order. Each group's block of Re H is passed as its rank and
        factors (``_block_factors``).
        """
        cache = getattr(self, "_packed", None)
        if cache is None:
            singles = self.single_modes()
            order = np.concatenate([singles, self.multi])
            lin = linear_vectors(self)
            n_single = singles.size
            rows = np.zeros((order.size, 12))
            rows[:, :3] = self.basis[:, order].T
            rows[:, 3:9] = lin[:, order].T
            rows[:n_single, 9] = self.q[order[:n_single]]
            ranks, factors = self.group_factors()
            cache = (np.ascontiguousarray(rows), n_single, np.ascontiguousarray(self.msizes, dtype=np.int64),
                     ranks, factors)
            self._packed = cache
        return cache


@dataclass
class _DataMap:
    """How join_exposures made z from the exposures' data: z = bincount(inv, conj(data[index]) zf) phase,
    data the exposures' rfft modes one after the other; for the exposures' noise variances and sizes."""

    zf: np.ndarray       # per joined mode, T w / (N sigma^2)
    index: np.ndarray    # per joined mode, its sampled mode in the concatenated data
    inv: np.ndarray      # per joined mode, the merged mode it went into
    sigma2: list
    sizes: list
    phase: np.ndarray    # per merged mode, the phase of the shifts applied since (shift_joint)

    def merged_z(self, exposures):
        """The exposures' cross-correlation weights, summed per merged mode (before the shifts' phase)."""
        data = np.concatenate([ex.data_ft for ex in exposures])[self.index]
        return complex_bincount(self.inv, np.conj(data) * self.zf, self.phase.size)


def _block_factors(A, sizes):
    """Factors of A's diagonal blocks (of ``sizes``; symmetric, positive semi-definite): per block of size p,
    vectors u_j with block = sum_j u_j u_j^T (eigenvectors times the root of their eigenvalues, those
    above 1e-13 of the largest), as (ranks, the u_j of every block one after the other)."""
    sizes = np.asarray(sizes, np.int64)
    starts = np.cumsum(sizes) - sizes
    ranks = np.zeros(sizes.size, np.int64)
    pieces = {}
    # the blocks' elements picked from a dense copy where it is small (sparse fancy indexing is slow)
    if sparse.issparse(A) and A.shape[0] <= 2048:
        A = A.toarray()
    for p in np.unique(sizes).tolist():
        g = np.nonzero(sizes == p)[0]
        idx = starts[g][:, None] + np.arange(p)[None]
        blocks = np.asarray(A[np.repeat(idx, p, axis=1).ravel(), np.tile(idx, (1, p)).ravel()]).reshape(g.size, p, p)
        w, v = np.linalg.eigh(blocks)                       # ascending eigenvalues
        w, v = w[:, ::-1], v[:, :, ::-1]
        keep = w > 1e-13 * np.maximum(w[:, :1], 1e-300)
        ranks[g] = keep.sum(axis=1)
        u = np.transpose(v * np.sqrt(np.maximum(w, 0.0))[:, None, :], (0, 2, 1))   # (block, j, n)
        pieces[p] = (g, u[keep].reshape(-1, p))               # the kept u_j, block after block
    n_fac = sizes * ranks
    fac_start = np.cumsum(n_fac) - n_fac
    out = np.zeros(int(n_fac.sum()))
    for p, (g, u) in pieces.items():
        lens = ranks[g] * p
        pos = np.repeat(fac_start[g] - (np.cumsum(lens) - lens), lens) + np.arange(int(lens.sum()))
        out[pos] = u.ravel()
    return ranks, out


def _packed_bins(jm, use_kernel=True):
    """Every mode, compact for binning (cached): (b3, c8, pair_basis, pair_a, pair_b, pair_h).

    b3: the basis [kx^2, 2 kx ky, ky^2, 0] and c8: the weights [lin0..lin5, q, 0] of every mode, in float32
    (the bins sum them in float64; 6e-8 relative per mode is far below the binning's own error), the modes
    alone on their sampled mode first, then the fold groups' (``jm.multi``), whose q is the diagonal of Re H.
    The groups' cross terms are the pairs (a < b) of their modes with Re H_ab != 0: pair_h = 2 Re H_ab, and
    pair_a, pair_b index pair_basis, the rows of b3 of the modes in a pair.
    """
    cache = getattr(jm, "_bins32", None)
    if cache is None:
        order, b3, qcol, pair_basis, pa, pb, ph = _bins_geometry(jm, use_kernel)
        c8 = np.empty((order.size, 8), np.float32)
        if use_kernel and USE_KERNEL:
            # the same numbers in one pass (bins_channels)
            KERNEL.bins_channels(order, np.ascontiguousarray(jm.z, dtype=complex),
                                 np.ascontiguousarray(jm.kx, dtype=float), np.ascontiguousarray(jm.ky, dtype=float),
                                 qcol, c8)
        else:
            # linear_vectors' rows in the modes' order, each made straight into its column
            for t, row in enumerate(_linear_rows(jm.z[order], jm.kx[order], jm.ky[order])):
                c8[:, t] = row
            c8[:, 6] = qcol
            c8[:, 7] = 0.0
        cache = jm._bins32 = (b3, c8, pair_basis, pa, pb, ph)
    return cache


#: :func:`_packed_bins` for the sampler's compiled chunks (sampling.EllipticityLikelihood._chunk_args)
packed_bins = _packed_bins


def _bins_geometry(jm, use_kernel=True):
    """What :func:`_packed_bins` takes from the modes alone, not from the data (cached, and carried by
    :meth:`JointModes.with_data` to another version's modes): the modes' order (alone on their sampled mode
    first, then the fold groups', as packed()'s, without its rows of doubles and the groups' factors, which
    only the unbinned kernel needs), b3, the q column (float32) and the fold groups' pairs (the rows of b3 of
    their modes, and per pair its two modes among them and 2 Re H_ab). The compiled kernel (``bins_geometry``;
    ``bins_channels`` for :func:`_packed_bins`' weights) makes the same arrays to the bit in one pass
    (tests/test_measure.py)."""
    cache = getattr(jm, "_bins32_geometry", None)
    if cache is None and use_kernel and USE_KERNEL:
        # the same arrays in one compiled call (bins_geometry)
        n = jm.n_modes
        H = jm.H.tocsr() if jm.multi.size else sparse.csr_matrix((0, 0), dtype=complex)
        order, b3, qcol = np.empty(n, np.int64), np.empty((n, 4), np.float32), np.empty(n, np.float32)
        got = KERNEL.bins_geometry(np.ascontiguousarray(jm.multi, dtype=np.int64),
                                   np.ascontiguousarray(jm.basis, dtype=float), np.ascontiguousarray(jm.q, dtype=float),
                                   np.ascontiguousarray(H.indptr, dtype=np.int64),
                                   np.ascontiguousarray(H.indices, dtype=np.int64),
                                   np.ascontiguousarray(H.data, dtype=complex), order, b3, qcol)
        gsel, pa, pb, ph = (np.frombuffer(b, dt) for b, dt in zip(got, (np.int64, np.int64, np.int64, float)))
        cache = (order, b3, qcol, np.ascontiguousarray(b3[gsel]), pa, pb, ph)
        for arr in cache:
            arr.setflags(write=False)
        jm._bins32_geometry = cache
    if cache is None:
        singles = jm.single_modes()
        n_single = singles.size
        order = np.concatenate([singles, jm.multi])
        n = order.size
        b3 = np.zeros((n, 4), np.float32)
        for t in range(3):   # (a row's gather at a time: the transposed gather of all three took 2.6 times as long)
            b3[:, t] = jm.basis[t, order]
        qcol = np.zeros(n, np.float32)
        qcol[:n_single] = jm.q[singles]
        pa = pb = np.zeros(0, np.int64)
        ph = np.zeros(0)
        gsel = np.zeros(0, np.int64)
        if jm.multi.size:
            H = jm.H.tocsr()
            hrow, hcol, hdata = _csr_entries(H)
            hdata = hdata.real
            qcol[n_single:] = H.diagonal().real
            up = (hrow < hcol) & (hdata != 0)
            rows, cols = hrow[up].astype(np.int64), hcol[up].astype(np.int64)
            gsel, inv = np.unique(np.concatenate([rows, cols]), return_inverse=True)
            pa, pb = np.ascontiguousarray(inv[:rows.size]), np.ascontiguousarray(inv[rows.size:])
            ph = np.ascontiguousarray(2.0 * hdata[up])
            gsel = np.ascontiguousarray(gsel + n_single, dtype=np.int64)
        cache = (order, b3, qcol, np.ascontiguousarray(b3[gsel]), pa.astype(np.int64), pb.astype(np.int64), ph)
        for arr in cache:
            arr.setflags(write=False)
        jm._bins32_geometry = cache
    return cache


#: bits of a positive double's pattern below the bucket index of ``_drop_threshold`` (the exponent and the
#: top 5 bits of the mantissa stay: buckets 3 % wide)
_BUCKET_SHIFT = 47


def _drop_threshold(b, tolerance, use_kernel=True):
    """The largest t among the values of ``b`` (>= 0) such that the sum of every b_j <= t is at most
    ``tolerance`` (None where even the smallest exceeds it): the weakest modes are dropped whole sets of
    equal bounds at a time, so that the cut does not depend on how a sort orders ties.

    The same t as sorting the values and summing them in order, without sorting them all: the values
    are summed in buckets of their bit patterns (monotonic in the value), and only the bucket where the
    sum crosses the tolerance is sorted (sums in another order than the sorted one's: the same t unless
    a sum lies within rounding of the tolerance).

    The compiled kernel (``KERNEL.drop_threshold``) makes the same t, its sums in the same order
    (tests/test_measure.py).
    """
    if use_kernel and USE_KERNEL:
        return KERNEL.drop_threshold(np.ascontiguousarray(b, dtype=float), float(tolerance))
    v = b[b <= tolerance] + 0.0
    if v.size == 0:
        return None
    key = v.view(np.int64) >> _BUCKET_SHIFT
    k0 = int(key.min())
    key = key - k0
    csum = np.cumsum(np.bincount(key, weights=v))
    j = int(np.searchsorted(csum, tolerance, side="right"))   # first bucket whose cumulative sum exceeds it
    if j < csum.size:
        w = np.sort(v[key == j])
        c = (float(csum[j - 1]) if j > 0 else 0.0) + np.cumsum(w)
        last = np.ones(w.size, bool)
        last[:-1] = w[1:] != w[:-1]
        ok = last & (c <= tolerance)
        if np.any(ok):
            return float(w[ok][-1])
    # no value of the crossing bucket qualifies: the largest of the buckets below it, if any
    return float(np.max(v[key < j])) if j > 0 else None


def _mode_bounds(exposures, use_kernel=True):
    """Per exposure, each mode's w |T_j|^2 / (N sigma^2), and S^2 for S the bound on the flux of the brightest
    model the data allow (a point source at 3 times its fitted flux plus 5 sigma; None where no mode has
    weight): a model's own term of chi^2 in a mode, w |S R T_j|^2 / (N sigma^2), is at most S^2 times its value
    (|R| <= 1). The compiled kernel (``KERNEL.mode_bound``, an exposure a call) makes the same values, its sums in
    order where numpy's are pairwise (the same to rounding; tests/test_measure.py)."""
    h = 0.0
    ff = 0.0
    bounds = []
    for ex in exposures:
        ny, nx = ex.shape
        norm = 1.0 / (ny * nx * ex.sigma2)
        if use_kernel and USE_KERNEL:
            p = np.empty(ex.coarse.size)
            he, fe = KERNEL.mode_bound(np.ascontiguousarray(ex.transfer, dtype=complex),
                                       np.ascontiguousarray(ex.coarse, dtype=np.int64),
                                       np.ascontiguousarray(ex.cweight, dtype=float),
                                       np.ascontiguousarray(ex.data_ft, dtype=complex), norm, p)
            h += he
            ff += fe
            bounds.append(p)
            continue
        w = ex.cweight[ex.coarse]
        p = w * np.abs(ex.transfer) ** 2 * norm
        h += float(np.sum((np.conj(ex.data_ft[ex.coarse]) * ex.transfer * w).real) * norm)
        ff += float(np.sum(p))
        bounds.append(p)
    if not ff > 0:
        return bounds, None
    return bounds, (3.0 * abs(h) / ff + 5.0 / np.sqrt(ff)) ** 2


def _noise_aware_cut(exposures, chi2_tolerance, mode_bounds=None):
    """Per exposure, the modes to keep so that the brightest model's own chi^2 in the dropped ones stays below
    ``chi2_tolerance``.

    A model's own term of chi^2 in mode j is at most S^2 w |T_j|^2/(N sigma^2)
    (|R| <= 1), S bounded from above by the point-source fit's flux: the
    weakest modes are dropped while their summed bound stays below the
    tolerance (all exposures together). The modes' cross terms with the data
    are not bounded so: dropping the modes drops their data, noise mostly, and
    with it a scatter of e that grows about as the square root of the tolerance
    (``benchmarks/speed.py --check`` reports it). ``mode_bounds``:
    :func:`_mode_bounds`'s, if already made.
    """
    bounds, s2 = _mode_bounds(exposures) if mode_bounds is None else mode_bounds
    if s2 is None:
        return [np.ones(b.size, bool) for b in bounds]
    allb = np.concatenate(bounds) * s2
    t = _drop_threshold(allb, chi2_tolerance)
    drop = allb <= t if t is not None else np.zeros(allb.size, bool)
    keep, start = [], 0
    for b in bounds:
        keep.append(~drop[start:start + b.size])
        start += b.size
    return keep


def _select(ex: ExposureModes, keep) -> ExposureModes:
    return ExposureModes(shape=ex.shape, kx=ex.kx[keep], ky=ex.ky[keep], transfer=ex.transfer[keep],
                         coarse=ex.coarse[keep], cweight=ex.cweight, data_ft=ex.data_ft, sigma2=ex.sigma2,
                         yy=ex.yy, npix=ex.npix, pixel_scale=ex.pixel_scale)


def _distinct_pairs(kx, ky):
    """(first, inv) of the distinct (kx, ky) pairs (exact equality), in np.unique's order of kx + i ky
    (lexicographic): the index of each pair's first occurrence and, per item, its pair's number."""
    if kx.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # the order of np.lexsort((arange, ky, kx)): by kx, then ky, then position, so that a pair's first occurrence
    # leads its run. kx alone first, by numpy's default sort (a sort of doubles several times faster than a stable
    # one or one of complex numbers); then only the runs of equal kx (with distinct Jacobians few: the exposures'
    # K = 0) are ordered by ky and position
    order = np.argsort(kx)
    sx = kx[order]
    tie = sx[1:] == sx[:-1]
    if np.any(tie):
        in_run = np.zeros(order.size, bool)
        in_run[1:] = tie
        in_run[:-1] |= tie
        at = np.nonzero(in_run)[0]
        run = np.cumsum(np.concatenate(([True], ~tie)))[at]
        sub = order[at]
        order[at] = sub[np.lexsort((sub, ky[sub], run))]
    sx, sy = kx[order], ky[order]
    new = np.empty(order.size, bool)
    new[0] = True
    new[1:] = (sx[1:] != sx[:-1]) | (sy[1:] != sy[:-1])
    inv = np.empty(order.size, np.int64)
    inv[order] = np.cumsum(new) - 1
    return order[new], inv


def _fold_groups(row, col, t, n, use_kernel=True):
    """The Parseval weights and fold groups of H = F^H F, F the sparse matrix of the entries ``t`` at
    (``row``, ``col``) (each pair at most once; rows ascending along the entries of each column), n columns.

    Returns (q, multi, msizes, Hm): q, H's diagonal (real) for the columns that share no row with another
    and 0 elsewhere; multi, the other columns, group after group (a group: the columns linked through
    shared rows, groups ordered by their first column, columns ascending within); msizes, the groups'
    sizes; Hm, H restricted to multi (csr, in multi's order). Each element of H is summed over its rows in
    ascending order, as a sparse product F^H F sums it.

    The compiled kernel (``KERNEL.fold_groups``: the groups by union-find, H's blocks summed row after row) makes
    the same groups and elements as the lines below, their values to rounding (numpy's complex products may fuse
    a multiply-add; tests/test_measure.py), without their array operations' overhead (0.34 ms a galaxy of
    ``benchmarks/speed.py``).
    """
    if use_kernel and USE_KERNEL:
        q = np.empty(n)
        got = KERNEL.fold_groups(np.ascontiguousarray(row, dtype=np.int64), np.ascontiguousarray(col, dtype=np.int64),
                                 np.ascontiguousarray(t, dtype=complex), int(n), q)
        if got is None:
            return q, np.zeros(0, np.int64), np.zeros(0, np.int64), sparse.csr_matrix((0, 0), dtype=complex)
        multi, msizes, data, indices, indptr = (np.frombuffer(b, dt) for b, dt in zip(
            got, (np.int64, np.int64, complex, np.int64, np.int64)))
        return q, multi, msizes, sparse.csr_matrix((data, indices, indptr), shape=(multi.size, multi.size))
    tt = (np.conj(t) * t).real
    counts = np.bincount(row)
    shared = counts[row] >= 2                        # entries on a row with another column
    linked = np.zeros(n, bool)
    linked[col[shared]] = True
    q = np.where(linked, 0.0, np.bincount(col, tt, n))
    m = np.nonzero(linked)[0]
    if m.size == 0:
        return q, m, np.zeros(0, np.int64), sparse.csr_matrix((0, 0), dtype=complex)
    # the groups: the components of the graph of linked columns and shared rows, each labelled by its first
    # column (a column takes the least label of its rows' columns until none changes)
    sel = np.nonzero(shared)[0]
    sel = sel[np.argsort(row[sel], kind="stable")]   # the shared entries, row after row
    rs, cs = row[sel], col[sel]
    heads = np.nonzero(np.concatenate([[True], rs[1:] != rs[:-1]]))[0]
    run = np.repeat(np.arange(heads.size), np.diff(np.append(heads, rs.size)))
    label = np.arange(n)
    while True:
        least = np.minimum.reduceat(label[cs], heads)[run]   # per entry, its row's least label
        if np.all(least >= label[cs]):
            break
        np.minimum.at(label, cs, least)
    multi = m[np.lexsort((m, label[m]))]
    lab = label[multi]
    starts = np.ones(lab.size, bool)
    starts[1:] = lab[1:] != lab[:-1]
    msizes = np.diff(np.append(np.nonzero(starts)[0], lab.size)).astype(np.int64)
    pos = np.full(n, -1, np.int64)
    pos[multi] = np.arange(multi.size)
    # H's terms on multi: every pair of the columns of a shared row, and each linked column's own terms on
    # rows it has alone
    k = counts[rs]                                   # the size of each entry's row
    a = np.repeat(np.arange(sel.size), k)            # each entry with every entry of its row (itself too)
    b = np.repeat(np.searchsorted(rs, rs), k) + (np.arange(a.size) - np.repeat(np.cumsum(k) - k, k))
    ea, eb = sel[a], sel[b]
    alone = np.nonzero(~shared & linked[col])[0]
    r_ = np.concatenate([row[ea], row[alone]])
    i_ = np.concatenate([pos[col[ea]], pos[col[alone]]])
    j_ = np.concatenate([pos[col[eb]], pos[col[alone]]])
    v_ = np.concatenate([np.conj(t[ea]) * t[eb], np.conj(t[alone]) * t[alone]])
    o = np.lexsort((r_, j_, i_))                     # by element, its rows ascending
    i_, j_, v_ = i_[o], j_[o], v_[o]
    head = np.ones(i_.size, bool)
    head[1:] = (i_[1:] != i_[:-1]) | (j_[1:] != j_[:-1])
    hs = np.nonzero(head)[0]
    data = np.add.reduceat(v_, hs)
    indptr = np.searchsorted(i_[hs], np.arange(multi.size + 1))
    Hm = sparse.csr_matrix((data, j_[hs], indptr), shape=(multi.size, multi.size))
    return q, multi, msizes, Hm


def _weak_couplings(msizes, Hm, s2, tolerance):
    """Which fold groups' cross terms can be dropped: a group's off-diagonal elements of H change any model's
    chi^2 by at most S^2 sum_(a != b) |H_ab| (|R| <= 1, ``s2`` = S^2 as in the noise-aware cut); the groups
    with the weakest such bounds are decoupled while their sum stays within ``tolerance``."""
    row, col, data = _csr_entries(Hm)
    gid = np.repeat(np.arange(msizes.size), msizes)
    off = row != col
    bound = np.bincount(gid[row[off]], np.abs(data[off]), msizes.size) * s2
    t = _drop_threshold(bound, tolerance)
    return bound <= t if t is not None else np.zeros(msizes.size, bool)


def _decouple(q, multi, msizes, Hm, decoupled):
    """The fold groups flagged in ``decoupled`` without their cross terms: their modes become modes alone on
    their sampled mode, with their diagonal elements of H as Parseval weights."""
    gid = np.repeat(np.arange(msizes.size), msizes)
    out = decoupled[gid]
    q = q.copy()
    q[multi[out]] = Hm.diagonal().real[out]
    stay = np.nonzero(~out)[0]
    # Hm[stay][:, stay] (a group's elements stay within the group: rows and columns of the kept ones)
    row, col, data = _csr_entries(Hm)
    new = np.full(multi.size, -1, np.int64)
    new[stay] = np.arange(stay.size)
    e = (new[row] >= 0) & (new[col] >= 0)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(new[row[e]], minlength=stay.size))])
    H = sparse.csr_matrix((data[e], new[col[e]], indptr), shape=(stay.size, stay.size))
    return q, multi[stay], msizes[~decoupled], H


def _csr_entries(H):
    """(row, col, data) of a csr matrix's stored entries, in its order."""
    row = np.repeat(np.arange(H.shape[0]), np.diff(H.indptr))
    return row, H.indices, H.data


def join_exposures(exposures: list[ExposureModes], chi2_tolerance: float = 0.0, keep=None,
                   fold_tolerance: float = 0.0, decoupled=None, pair_tolerance: float = 0.0,
                   use_kernel=True) -> JointModes:
    """Concatenate the exposures' modes (after the noise-aware cut, if a tolerance is given).

    ``keep`` (per exposure, a boolean mask of its modes) imposes the modes
    another fit kept instead of cutting afresh; the masks used are
    ``result.keep`` (None: no cut). With ``fold_tolerance`` > 0 (and no
    ``keep``), the fold groups whose cross terms matter least are decoupled
    (:func:`_weak_couplings`); ``decoupled`` (per fold group, as
    ``result.decoupled``) imposes another fit's choice. With ``pair_tolerance`` > 0, each model's sums
    leave out the fold groups' remaining cross terms where, for that model at the brightest flux the data
    allow, they could change chi^2 by at most this (``result.pair_skip``; the binned sums only).

    The modes' concatenation and merging are compiled (``KERNEL.join_gather``, ``KERNEL.join_distinct``: the
    same arrays as the numpy lines below, which ``use_kernel=False`` runs and which stay as the reference).
    """
    mb = _mode_bounds(exposures) if keep is None and (chi2_tolerance > 0 or fold_tolerance > 0) else None
    s2 = None
    if pair_tolerance > 0:
        s2 = (mb if mb is not None else _mode_bounds(exposures))[1]
    if keep is None and chi2_tolerance > 0:
        keep = _noise_aware_cut(exposures, chi2_tolerance, mb)
    if use_kernel and USE_KERNEL:
        return _join_kernel(exposures, keep, mb, s2, fold_tolerance, decoupled, pair_tolerance)
    if keep is not None:
        exposures = [_select(ex, k) for ex, k in zip(exposures, keep)]
    kx, ky, zf, tscaled, group = [], [], [], [], []
    goffset = 0
    yy = 0.0
    npix = 0
    for ex in exposures:
        ny, nx = ex.shape
        norm = 1.0 / (ny * nx * ex.sigma2)
        w = ex.cweight[ex.coarse]
        zf.append(ex.transfer * w * norm)
        tscaled.append(ex.transfer * np.sqrt(w * norm))
        group.append(ex.coarse + goffset)
        goffset += ex.cweight.size
        kx.append(ex.kx)
        ky.append(ex.ky)
        yy += ex.yy
        npix += ex.npix
    kx = np.concatenate(kx)
    ky = np.concatenate(ky)
    zf = np.concatenate(zf)
    tscaled = np.concatenate(tscaled)
    group = np.concatenate(group)
    # one mode per distinct K (exactly equal: exposures with equal Jacobians)
    first, inv = _distinct_pairs(kx, ky)
    n = first.size
    dmap = _DataMap(zf=zf, index=group, inv=inv, sigma2=[ex.sigma2 for ex in exposures],
                    sizes=[ex.cweight.size for ex in exposures], phase=np.ones(n, complex))
    zu = dmap.merged_z(exposures)
    # F: the exposures' sampled modes (rows) from the transforms at the distinct K (columns); H = F^H F
    # the sampled modes used, numbered in order (np.unique's, without a sort)
    present = np.zeros(goffset, bool)
    present[group] = True
    grow = (np.cumsum(present) - 1)[group]
    return _joint_modes(exposures, kx[first], ky[first], zu, dmap, grow, inv, tscaled, yy, npix, keep, mb, s2,
                        fold_tolerance, decoupled, pair_tolerance)


def _join_kernel(exposures, keep, mb, s2, fold_tolerance, decoupled, pair_tolerance):
    """join_exposures' concatenation and merging compiled (``KERNEL.join_gather``, numpy's complex product,
    ``KERNEL.join_distinct`` with its own stable radix sort of kx, about 3 times numpy's argsort's speed on a fit's
    5e3 modes): the same arrays as its numpy lines, to the bit."""
    c = np.ascontiguousarray
    items = tuple((c(ex.kx, dtype=float), c(ex.ky, dtype=float), c(ex.transfer, dtype=complex),
                   c(ex.coarse, dtype=np.int64), c(ex.cweight, dtype=float), c(ex.data_ft, dtype=complex).ravel(),
                   int(ex.shape[0]), int(ex.shape[1]), float(ex.sigma2)) for ex in exposures)
    keeps = tuple(b"" if keep is None else c(k, dtype=np.uint8) for k in (keep or exposures))
    kxb, kyb, zfb, tsb, grb, dab, goffset = KERNEL.join_gather(items, keeps)
    kx, ky = np.frombuffer(kxb, float), np.frombuffer(kyb, float)
    zf, tscaled = np.frombuffer(zfb, complex), np.frombuffer(tsb, complex)
    group = np.frombuffer(grb, np.int64)
    zdat = np.conj(np.frombuffer(dab, complex)) * zf
    fb, ib, zb, gb = KERNEL.join_distinct(kx, ky, b"", zdat, group, goffset)
    first, inv, grow = np.frombuffer(fb, np.int64), np.frombuffer(ib, np.int64), np.frombuffer(gb, np.int64)
    zu = np.frombuffer(zb, complex).copy()
    yy = 0.0
    npix = 0
    for ex in exposures:
        yy += ex.yy
        npix += ex.npix
    dmap = _DataMap(zf=zf, index=group, inv=inv, sigma2=[ex.sigma2 for ex in exposures],
                    sizes=[ex.cweight.size for ex in exposures], phase=np.ones(first.size, complex))
    return _joint_modes(exposures, kx[first], ky[first], zu, dmap, grow, inv, tscaled, yy, npix, keep, mb, s2,
                        fold_tolerance, decoupled, pair_tolerance)


def _joint_modes(exposures, kxu, kyu, zu, dmap, grow, inv, tscaled, yy, npix, keep, mb, s2, fold_tolerance,
                 decoupled, pair_tolerance):
    """join_exposures' JointModes from its merged modes: the fold groups, decoupled where they matter least."""
    n = kxu.size
    q, multi, msizes, Hm = _fold_groups(grow, inv, tscaled, n)
    if decoupled is None and mb is not None and mb[1] is not None and fold_tolerance > 0 and msizes.size:
        decoupled = _weak_couplings(msizes, Hm, mb[1], fold_tolerance)
    if decoupled is not None:
        decoupled = np.asarray(decoupled, bool)
        if decoupled.size != msizes.size:
            raise ShearfitValueError(f"join_exposures: decoupled= has {decoupled.size} fold groups, the modes "
                                     f"{msizes.size}")
        if np.any(decoupled):
            q, multi, msizes, Hm = _decouple(q, multi, msizes, Hm, decoupled)
    return JointModes(kx=kxu, ky=kyu, z=zu, q=q, multi=multi, msizes=msizes, H=Hm,
                      basis=np.stack([kxu * kxu, 2 * kxu * kyu, kyu * kyu]), yy=yy, npix=npix,
                      n_exposures=len(exposures), pixel_scale=float(np.mean([e.pixel_scale for e in exposures])),
                      keep=keep, decoupled=decoupled, data_map=dmap,
                      pair_skip=pair_tolerance / s2 if s2 else 0.0)


def shift_phase(kx, ky, du, dv, use_kernel=True):
    """exp(-i (kx du + ky dv)): the compiled kernel's (``shift_phase``: the C library's cos and sin, which numpy's
    complex exp of a purely imaginary number is) or numpy's, the same numbers (a test checks them)."""
    if use_kernel and USE_KERNEL:
        out = np.empty(kx.size, complex)
        KERNEL.shift_phase(np.ascontiguousarray(kx, dtype=float), np.ascontiguousarray(ky, dtype=float), float(du),
                           float(dv), out)
        return out
    return np.exp(-1j * (kx * du + ky * dv))


def shift_joint(jm: JointModes, du, dv) -> JointModes:
    """The same modes with the model origin moved by (du, dv) arcsec on the sky."""
    phase = shift_phase(jm.kx, jm.ky, du, dv)
    H = jm.H
    if jm.multi.size:
        # diag(conj(ph)) H diag(ph), on H's own pattern
        ph = phase[jm.multi]
        Hc = sparse.csr_matrix(jm.H)
        rows = np.repeat(np.arange(Hc.shape[0]), np.diff(Hc.indptr))
        H = sparse.csr_matrix(((np.conj(ph[rows]) * Hc.data) * ph[Hc.indices], Hc.indices.copy(), Hc.indptr.copy()),
                              shape=Hc.shape)
    dm = jm.data_map
    if dm is not None:
        dm = replace(dm, phase=dm.phase * phase)
    out = JointModes(kx=jm.kx, ky=jm.ky, z=jm.z * phase, q=jm.q, multi=jm.multi, msizes=jm.msizes, H=H,
                     basis=jm.basis, yy=jm.yy, npix=jm.npix, n_exposures=jm.n_exposures,
                     pixel_scale=jm.pixel_scale, keep=jm.keep, decoupled=jm.decoupled, data_map=dm,
                     pair_skip=jm.pair_skip)
    if not jm.multi.size:
        # without fold groups nothing but the data moves: what the modes alone give is shared (so that versions
        # of an object at their own positions still bin together: mode_bins_versions)
        for name in ("_factors", "_bins32_geometry"):
            cached = getattr(jm, name, None)
            if cached is not None:
                setattr(out, name, cached)
    return out


@dataclass
class ModelSums:
    """Pixel sums of a batch of models (arrays over models)."""

    hf: np.ndarray
    hg: np.ndarray
    grad_f: np.ndarray   # (n, 2) d h_f / d(u, v) at the reference position
    grad_g: np.ndarray
    hess_f: np.ndarray   # (n, 3) d2 h_f / (du du, du dv, dv dv)
    hess_g: np.ndarray
    ff: np.ndarray
    gg: np.ndarray
    fg: np.ndarray

    @classmethod
    def from_kernel(cls, out):
        """Views into the kernels' (n, 15) output [hf, grad_f, hess_f, hg, grad_g, hess_g, ff, gg, fg]."""
        s = cls(hf=out[:, 0], hg=out[:, 6], grad_f=out[:, 1:3], grad_g=out[:, 7:9], hess_f=out[:, 3:6],
                hess_g=out[:, 9:12], ff=out[:, 12], gg=out[:, 13], fg=out[:, 14])
        s._packed = out
        return s

    def packed(self):
        """The sums as one C-contiguous (n, 15) array in the kernels' layout."""
        out = getattr(self, "_packed", None)
        if out is None:
            out = np.column_stack([self.hf, self.grad_f, self.hess_f, self.hg, self.grad_g, self.hess_g,
                                   self.ff, self.gg, self.fg])
        return np.ascontiguousarray(out, dtype=float)


def _linear_rows(z, kx, ky):
    """The six linear vectors of modes (z, kx, ky), one array each: h(x) = sum R Re(z exp(-i K.x)), its value,
    gradient and Hessian at x = 0."""
    zr, zi = z.real, z.imag
    return zr, kx * zi, ky * zi, -kx * kx * zr, -kx * ky * zr, -ky * ky * zr


def linear_vectors(jm: JointModes):
    return np.stack(_linear_rows(jm.z, jm.kx, jm.ky))


def _model_sums_kernel(jm, coef, fast, ratio):
    out = np.empty((coef.shape[0], 15))
    packed, n_single, gsizes, granks, factors = jm.packed()
    KERNEL.model_sums(np.ascontiguousarray(coef), packed, fast.packed32, fast.C, 1.0 / fast.du,
                        float(ratio) ** 2, n_single, gsizes, granks, factors, out)
    return ModelSums.from_kernel(out)


@dataclass
class ModeBins:
    """An object's modes summed in bins of K^T C K, per ellipticity (see :func:`mode_bins`)."""

    shape: np.ndarray      # (n_e, 3): c11, c12, c22 of each ellipticity
    bins_per_octave: int
    lo: bytes              # int64 per ellipticity: its first bin (kappa = 2^(lo / bins_per_octave))
    offsets: bytes         # int64, n_e + 1: ellipticity i's bins are columns offsets[i]:offsets[i + 1]
    columns: bytes         # float64: the bins' weights (six linear vectors, q), channel after channel
    dc: bytes              # float64 (n_e, 8): the DC mode's weights


def polar_setting(cfg):
    """(angles, e_max) of a FitConfig's polar grid (:func:`mode_bins`), or None where it is off."""
    n = int(cfg.mode_polar_angles)
    return (n, float(cfg.mode_polar_e_max)) if n > 0 else None


def polar_args(grid, polar):
    """make_bins' polar argument: the grid (KERNEL.polar_grid's), its angles and the least q^2 binned from it."""
    n, e_max = polar
    q = (1.0 - e_max) / (1.0 + e_max)
    return grid + (n, q * q)


#: the polar grid's cost model (:func:`polar_pays`), ns per ellipticity on an AMD EPYC Zen 4 with the AVX2 loops
#: (benchmarks/README.md, session 77): binning mode by mode POLAR_DIRECT_NS + POLAR_MODE_NS per mode; from the grid
#: POLAR_NODE_NS per node, plus the grid's making (70 ns per mode an object) over about 260 ellipticities
POLAR_DIRECT_NS, POLAR_MODE_NS, POLAR_NODE_NS, POLAR_SPREAD_NS = 1460.0, 3.62, 1.3, 0.27
#: a mode binned by itself costs this many of the grid's nodes: the grid leaves off the modes of its lowest rows,
#: where they are fewer than a row's nodes pay for (``_kernels.c``, polar_grid)
POLAR_NODE_MODES = POLAR_MODE_NS / POLAR_NODE_NS


def polar_pays(jm: JointModes, bins_per_octave, angles) -> bool:
    """Whether binning from the polar grid (:func:`mode_bins`) costs less than binning every mode, for these
    modes: their number against the grid's nodes (``angles`` columns over the modes' range of log |K|^2, a node every
    second bin). Exposures that share a Jacobian merge their modes (dithers only change phases), and a thousand
    modes cost less mode by mode than the grid's nodes (cached; the modes alone decide it, not the machine)."""
    key = (int(bins_per_octave), int(angles))
    cache = getattr(jm, "_polar_pays", None)
    if cache is None or cache[0] != key:
        b3 = _packed_bins(jm)[0]
        k2 = b3[:, 0].astype(float) + b3[:, 2]
        k2 = k2[k2 > 0]
        n = k2.size
        nodes = key[1] * (0.5 * key[0] * np.log2(k2.max() / k2.min()) + 3.0) if n else 0.0
        pays = n > 0 and POLAR_NODE_NS * nodes + POLAR_SPREAD_NS * n < POLAR_DIRECT_NS + POLAR_MODE_NS * n
        cache = jm._polar_pays = (key, bool(pays))
    return cache[1]


def _aligned_grid(grid):
    """KERNEL.polar_grid's output with the grid's floats copied to 64-byte boundaries, as make_bins reads them
    (it copies a grid that is not, at every call)."""
    u0, n_u, g, dc, rows, direct = grid
    raw = np.frombuffer(g, np.uint8)
    buf = np.empty(raw.size + 64, np.uint8)
    off = -buf.ctypes.data % 64
    out = buf[off:off + raw.size]
    out[:] = raw
    return u0, n_u, out, dc, rows, direct


def polar_grid(jm: JointModes, bins_per_octave, angles):
    """The object's modes spread onto the polar grid of :func:`mode_bins` (cached per bins and angles):
    KERNEL.polar_grid's (u0, n_u, grid, dc, rows), the grid's float32 on 64-byte boundaries."""
    key = (int(bins_per_octave), int(angles))
    cache = getattr(jm, "_polar", None)
    if cache is None or cache[0] != key:
        b3, c8 = _packed_bins(jm)[:2]
        cache = jm._polar = (key, _aligned_grid(KERNEL.polar_grid(b3, c8, key[0], key[1], 1, POLAR_NODE_MODES)))
    return cache[1]


def seed_polar_grid(jm: JointModes, bins_per_octave, angles, grid):
    """Give these modes the polar grid :func:`polar_grid` would make for them, made elsewhere (a version's blocks of
    its versions' grid, :func:`versions_polar_subset`), where they have none yet."""
    key = (int(bins_per_octave), int(angles))
    cache = getattr(jm, "_polar", None)
    if cache is None or cache[0] != key:
        jm._polar = (key, grid)


#: a thread's memory for the columns of make_bins (:func:`mode_bins`' ``reuse``)
_COLUMNS = threading.local()


def column_buffer():
    """This thread's memory for make_bins' columns (:func:`_binned`'s ``reuse``)."""
    buf = getattr(_COLUMNS, "array", None)
    if buf is None:
        buf = _COLUMNS.array = np.empty(0)
    return buf


def grow_column_buffer(n):
    """A larger :func:`column_buffer` for the next call, after make_bins needed ``n`` doubles that did not fit."""
    _COLUMNS.array = np.empty(int(1.5 * n) + 1024)


def _binned(shape, b3, c8, bins_per_octave, nv, polar_args, reuse):
    """KERNEL.make_bins' (lo, offsets, columns, dc); with ``reuse`` the columns are written into this thread's
    buffer, kept from one call to the next (its memory already mapped), and returned as a view of it: valid only
    until the next call with ``reuse`` in the same thread. Where they do not fit, make_bins returns them in
    memory of their own, and the buffer grows for the next call."""
    if not reuse:
        return KERNEL.make_bins(shape, b3, c8, int(bins_per_octave), nv, polar_args)
    buf = column_buffer()
    lo, offsets, columns, dc = KERNEL.make_bins(shape, b3, c8, int(bins_per_octave), nv, polar_args, buf)
    if columns is None:
        columns = buf[:7 * int(np.frombuffer(offsets, np.int64)[-1])]   # (7: make_bins' channels)
    else:
        grow_column_buffer(len(columns) / 8)
    return lo, offsets, columns, dc


def mode_bins(jm: JointModes, e1, e2, bins_per_octave, polar=None, reuse=False) -> ModeBins:
    """Bin the modes for each ellipticity (e1[i], e2[i]), in K^T C K, ``bins_per_octave`` bins per factor of
    2, uniform in log K^T C K (each mode shared among four bins by cubic interpolation). Models of any size
    at one of these ellipticities then cost one evaluation per bin instead of per mode (:func:`model_sums`,
    ``bins``); the fold groups' cross terms, one product per pair of modes, with the modes' transforms
    interpolated from the bins' (see :func:`_packed_bins`).

    ``polar``: (angles, e_max) (:func:`polar_setting`). The modes are then spread once onto a grid uniform in
    log |K|^2 (a node every second bin) and in the direction of K (``angles`` nodes over 180 deg), and the
    ellipticities up to ``e_max`` are binned from its nodes: K^T C K = |K|^2 A(direction), so every node of one
    direction moves along the bins' axis by the same log A, and a whole column of nodes is shared among the bins
    with one set of weights (``_kernels.c``, polar_grid). The cost no longer grows with the number of modes
    (exposures); the sums are right to sixth order in the nodes' spacing in log |K|^2 and in angle. The modes of
    the grid's lowest rows, fewer there than a row's nodes pay for (``POLAR_NODE_MODES``), are left off it and
    binned one by one. Where the modes are fewer than the grid's nodes pay for (:func:`polar_pays`: exposures
    sharing a Jacobian), every mode is binned as without ``polar``.

    ``reuse``: the columns written into memory this thread keeps from one call to the next, valid only until its
    next call with ``reuse`` (the sampler's chunks, whose bins live within the chunk: :func:`_binned`)."""
    shape = np.ascontiguousarray(np.stack(shape_matrix(np.atleast_1d(np.asarray(e1, float)),
                                                       np.atleast_1d(np.asarray(e2, float))), axis=1))
    b3, c8 = _packed_bins(jm)[:2]
    pargs = (polar_args(polar_grid(jm, bins_per_octave, polar[0]), polar)
             if polar is not None and polar_pays(jm, bins_per_octave, polar[0]) else None)
    lo, offsets, columns, dc = _binned(shape, b3, c8, bins_per_octave, 1, pargs, reuse)
    return ModeBins(shape=shape, bins_per_octave=int(bins_per_octave), lo=lo, offsets=offsets, columns=columns,
                    dc=dc)


def shares_bins_geometry(jms) -> bool:
    """Whether JointModes (versions of one object: :meth:`JointModes.with_data`'s) share the modes' geometry,
    so that :func:`mode_bins_versions` can bin them together."""
    b3 = _packed_bins(jms[0])[0]
    return all(_packed_bins(j)[0] is b3 for j in jms[1:])


def versions_channels(jms) -> np.ndarray:
    """The versions' binned weights (:func:`_packed_bins`' c8) one after the other, for
    :func:`mode_bins_versions`."""
    if not shares_bins_geometry(jms):
        raise ShearfitValueError("mode_bins_versions: the versions do not share their modes")
    return np.concatenate([_packed_bins(j)[1] for j in jms])


def versions_polar_grid(jms, channels, bins_per_octave, angles):
    """The polar grid (:func:`mode_bins`) of versions of one object (their :func:`versions_channels`), for
    :func:`mode_bins_versions`: each version's grid is the one its own :func:`polar_grid` makes."""
    b3 = _packed_bins(jms[0])[0]
    return _aligned_grid(KERNEL.polar_grid(b3, channels, int(bins_per_octave), int(angles), len(jms),
                                           POLAR_NODE_MODES))


def versions_polar_subset(grid, versions, nv):
    """The polar grid of the versions ``versions`` (indices) of the ``nv`` whose :func:`versions_polar_grid` is
    ``grid``: their blocks of it (each version's grid is spread from its own weights alone, on node rows and
    columns that only the modes decide), as that function makes it for them."""
    u0, n_u, g, dc, rows, direct = grid
    vsz = g.size // nv
    dsz = len(dc) // nv
    pick = [int(v) for v in versions]
    sub_g = np.concatenate([g[v * vsz:(v + 1) * vsz] for v in pick]).tobytes()
    sub_dc = b"".join(dc[v * dsz:(v + 1) * dsz] for v in pick)
    return _aligned_grid((u0, n_u, sub_g, sub_dc, rows, direct))


def mode_bins_versions(jms, e1, e2, bins_per_octave, channels=None, polar=None, grid=None, reuse=False) -> ModeBins:
    """:func:`mode_bins` of several versions of one object at once (JointModes on the same modes, with other
    data: :func:`shares_bins_geometry`): entry ``i * V + v`` of the result is version v's bins at
    ellipticity i, the same numbers as ``mode_bins(jms[v], ...)``'s entry i. Each ellipticity's bin
    positions and interpolation weights are found once for the V versions. ``channels``:
    :func:`versions_channels` of ``jms``, made once for many calls; ``polar`` as :func:`mode_bins`'s (the
    versions' shared modes decide whether it pays), with ``grid`` :func:`versions_polar_grid`'s (made here if
    None); ``reuse`` as :func:`mode_bins`'."""
    nv = len(jms)
    c8 = versions_channels(jms) if channels is None else channels
    shape = np.ascontiguousarray(np.stack(shape_matrix(np.atleast_1d(np.asarray(e1, float)),
                                                       np.atleast_1d(np.asarray(e2, float))), axis=1))
    b3 = _packed_bins(jms[0])[0]
    pargs = None
    if polar is not None and polar_pays(jms[0], bins_per_octave, polar[0]):
        if grid is None:
            grid = versions_polar_grid(jms, c8, bins_per_octave, polar[0])
        pargs = polar_args(grid, polar)
    lo, offsets, columns, dc = _binned(shape, b3, c8, bins_per_octave, nv, pargs, reuse)
    return ModeBins(shape=np.ascontiguousarray(np.repeat(shape, nv, axis=0)), bins_per_octave=int(bins_per_octave),
                    lo=lo, offsets=offsets, columns=columns, dc=dc)


def bins_context(jm, bins, fast, ratio):
    """What the compiled binned sums take besides the models (``KERNEL.binned_sums``' other arguments, in its
    order; ``KERNEL.size_nodes`` takes them as one tuple): the bins, the log tables of ``fast`` and the fold
    groups' pairs."""
    return (bins.shape, bins.lo, bins.offsets, bins.columns, bins.dc, bins.bins_per_octave) + bins_context_rest(
        jm, fast, bins.bins_per_octave, ratio)


def bins_context_rest(jm, fast, bins_per_octave, ratio):
    """:func:`bins_context`'s items after bins_per_octave: the log tables of ``fast`` and the fold groups' pairs."""
    _, _, pair_basis, pa, pb, ph = _packed_bins(jm)
    lt = fast.log_table(bins_per_octave)
    return (lt.rows[0], lt.rows[1], lt.m, lt.n_col, lt.start, lt.per_octave, lt.low[0], lt.low[1], lt.zero[0],
            lt.zero[1], float(ratio) ** 2, pair_basis, pa, pb, ph, float(jm.pair_skip))


def _model_sums_binned(jm, bins, e_index, r2, fast, ratio):
    out = np.empty((r2.size, 15))
    ctx = bins_context(jm, bins, fast, ratio)   # (binned_sums takes the models after the context's first item)
    KERNEL.binned_sums(ctx[0], np.ascontiguousarray(r2), np.ascontiguousarray(e_index, dtype=np.int64), *ctx[1:],
                       out)
    return ModelSums.from_kernel(out)


def _is_plus_zero(x):
    return x == 0.0 and not math.copysign(1.0, x) < 0


def _round_bins(jm, bins_per_octave):
    """:func:`mode_bins` of these modes at e = (+0, +0), kept with them: the round models of the size range and the
    likelihood's point source share it (one binning of every mode a fit)."""
    cache = getattr(jm, "_round", None)
    if cache is None or cache[0] != int(bins_per_octave):
        cache = jm._round = (int(bins_per_octave), mode_bins(jm, np.zeros(1), np.zeros(1), bins_per_octave))
    return cache[1]


def seed_round_bins(jms, bins_per_octave):
    """:func:`_round_bins` of versions of one object (JointModes on the same modes, :func:`shares_bins_geometry`)
    made in one binning (:func:`mode_bins_versions` at e = (+0, +0)), each kept with its version: the same numbers
    as its own (metacal's replays' point sources). Nothing where fewer than two need them, they do not share their
    modes, or the compiled kernel is off."""
    bpo = int(bins_per_octave)
    need = [j for j in jms if getattr(j, "_round", (None,))[0] != bpo]
    if len(need) < 2 or not USE_KERNEL or bpo <= 0 or not shares_bins_geometry(need):
        return
    both = mode_bins_versions(need, np.zeros(1), np.zeros(1), bpo)
    lo, off = np.frombuffer(both.lo, np.int64), np.frombuffer(both.offsets, np.int64)
    cols, dc = np.frombuffer(both.columns, np.float64), np.frombuffer(both.dc, np.float64)
    for v, jm in enumerate(need):   # version v's entry: its bins' columns (seven channels), DC weights and start
        a, b = int(off[v]), int(off[v + 1])
        jm._round = (bpo, ModeBins(shape=np.ascontiguousarray(both.shape[v:v + 1]), bins_per_octave=bpo,
                                   lo=lo[v:v + 1].tobytes(), offsets=np.array([0, b - a], np.int64).tobytes(),
                                   columns=cols[7 * a:7 * b].tobytes(), dc=dc[8 * v:8 * v + 8].tobytes()))


def model_sums(jm: JointModes, e1, e2, r, fast, bulge_size_ratio=1.0, lin=None, use_kernel=True,
               bins_per_octave=0, bins=None, bin_index=None) -> ModelSums:
    """Pixel sums for models (e1, e2, r) (1D arrays of equal length).

    ``fast`` is a :class:`shearfit.engine.profiles.FastRadial` holding the disk (0)
    and bulge (1) transforms. With ``bins_per_octave`` > 0 (and the
    compiled kernel), the modes alone on their sampled mode are summed in
    bins of K^T C K, that many per factor of 2, once per run of consecutive
    models with one ellipticity (see ``FitConfig.mode_bins_per_octave``);
    0 evaluates every mode. ``bins`` (from :func:`mode_bins`) and
    ``bin_index`` (per model, its ellipticity's index in ``bins``) reuse
    bins already made.
    """
    e1 = np.atleast_1d(np.asarray(e1, float))
    r = np.atleast_1d(np.asarray(r, float))
    if r.shape != e1.shape:
        r = np.broadcast_to(r, e1.shape)
    r2 = r * r
    if USE_KERNEL and use_kernel and bins is not None:
        return _model_sums_binned(jm, bins, bin_index, r2, fast, bulge_size_ratio)
    e2 = np.atleast_1d(np.asarray(e2, float))
    if USE_KERNEL and use_kernel and bins_per_octave > 0:
        # runs of consecutive models with one ellipticity share their bins
        new = np.ones(e1.size, bool)
        new[1:] = (e1[1:] != e1[:-1]) | (e2[1:] != e2[:-1])
        starts = np.nonzero(new)[0]
        if starts.size == 1 and _is_plus_zero(e1[0]) and _is_plus_zero(e2[0]):
            bins = _round_bins(jm, bins_per_octave)
        else:
            bins = mode_bins(jm, e1[starts], e2[starts], bins_per_octave)
        return _model_sums_binned(jm, bins, np.cumsum(new) - 1, r2, fast, bulge_size_ratio)
    c11, c12, c22 = shape_matrix(e1, e2)
    coef = np.stack([c11 * r2, c12 * r2, c22 * r2], axis=1)
    if USE_KERNEL and use_kernel:
        return _model_sums_kernel(jm, coef, fast, bulge_size_ratio)
    if lin is None:
        lin = linear_vectors(jm)
    # the numpy lines hold a few (models x modes) arrays: in blocks of models, so that each stays near
    # NUMPY_BLOCK_ELEMENTS (all at once, a sampler's chunk of 256 ellipticities took 120-240 MB, against the
    # 9-25 MB pipeline.memory estimates; in blocks 6-11 MB, and the fits 2.7 times faster: 688 -> 255 ms a
    # speed.py galaxy)
    block = max(1, NUMPY_BLOCK_ELEMENTS // max(jm.n_modes, 1))
    if coef.shape[0] > block:
        parts = [_model_sums_numpy(jm, coef[i:i + block], fast, bulge_size_ratio, lin)
                 for i in range(0, coef.shape[0], block)]
        return ModelSums(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                            for f in fields(ModelSums)})
    return _model_sums_numpy(jm, coef, fast, bulge_size_ratio, lin)


#: the numpy lines' model sums (no compiled kernel) take this many (model, mode) pairs at a time
NUMPY_BLOCK_ELEMENTS = 2 ** 16


def _model_sums_numpy(jm, coef, fast, bulge_size_ratio, lin):
    """model_sums' numpy lines for the models of ``coef`` (rows: c11 r^2, c12 r^2, c22 r^2)."""
    rho2 = coef @ jm.basis
    i, frac = fast.index(rho2)
    Rf = fast.lookup(0, i, frac)
    if bulge_size_ratio != 1.0:
        i, frac = fast.index(rho2 * (bulge_size_ratio ** 2))
    Rg = fast.lookup(1, i, frac)
    Lf = Rf @ lin.T
    Lg = Rg @ lin.T
    ff = (Rf * Rf) @ jm.q
    gg = (Rg * Rg) @ jm.q
    fg = (Rf * Rg) @ jm.q
    if jm.multi.size:
        # the fold groups: R_m^T Re(H) R_m
        Hr = sparse.csr_matrix(jm.H.real)
        Rfm, Rgm = Rf[:, jm.multi], Rg[:, jm.multi]
        HRf = (Hr @ Rfm.T).T
        ff = ff + np.sum(HRf * Rfm, axis=1)
        gg = gg + np.sum((Hr @ Rgm.T).T * Rgm, axis=1)
        fg = fg + np.sum(HRf * Rgm, axis=1)
    return ModelSums(hf=Lf[:, 0], hg=Lg[:, 0], grad_f=Lf[:, 1:3], grad_g=Lg[:, 1:3],
                     hess_f=Lf[:, 3:6], hess_g=Lg[:, 3:6], ff=ff, gg=gg, fg=fg)


# --------------------------------------------------------------------------
# special functions in log space
# --------------------------------------------------------------------------

def log_erf_diff(a, b):
    """log(erf(a) - erf(b)) for a > b, without cancellation in the tails."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    a, b = np.broadcast_arrays(a, b)
    out = np.empty(a.shape)
    # both in the upper tail: erf(a)-erf(b) = erfc(b) - erfc(a) = e^{-b^2}[erfcx(b) - erfcx(a) e^{b^2-a^2}]
    up = b >= 0
    ab, bb = a[up], b[up]
    out[up] = -bb * bb + np.log(special.erfcx(bb) - special.erfcx(ab) * np.exp(bb * bb - ab * ab))
    lo = a <= 0
    # mirror image of the upper tail
    al, bl = -b[lo], -a[lo]
    out[lo] = -bl * bl + np.log(special.erfcx(bl) - special.erfcx(al) * np.exp(bl * bl - al * al))
    mid = ~(up | lo)
    out[mid] = np.log(special.erf(a[mid]) - special.erf(b[mid]))
    return out


_EI_SERIES_FROM = 40.0
# coefficients k! of the asymptotic series Ei(x) ~ (e^x / x) sum_k k! / x^k, to k = 12: at x >= 40 the
# first omitted term, 13!/40^13, is 1e-11 of the sum (the series is used where it is that good)
_EI_FACTORIALS = np.cumprod(np.concatenate([[1.0], np.arange(1.0, 13.0)]))


def _log_ei(x):
    """log Ei(x) for x > 0.37 (where Ei > 0): scipy's expi below 40, the asymptotic series beyond."""
    x = np.asarray(x, float)
    out = np.empty(x.shape)
    small = x < _EI_SERIES_FROM
    if np.any(small):
        out[small] = np.log(special.expi(x[small]))
    xl = x[~small]
    inv = 1.0 / xl
    series = np.zeros_like(xl)
    for c in _EI_FACTORIALS[::-1]:
        series = series * inv + c
    out[~small] = xl - np.log(xl) + np.log(series)
    return out


def log_ei_minus(A, t):
    """log(Ei(A) - Ei(t)) for A > t > 0.37; -inf where A <= t."""
    A = np.asarray(A, float)
    out = np.full(A.shape, -np.inf)
    ok = A > t
    if np.any(ok):
        la = _log_ei(A[ok])
        lt = float(_log_ei(np.array([t]))[0])
        out[ok] = la + np.log1p(-np.exp(lt - la))
    return out


# --------------------------------------------------------------------------
# bulge fraction, position and flux marginalisation
# --------------------------------------------------------------------------

def _disk_logp(S, ff, gg, fg, hf, hg, cfg: FitConfig, log_zb):
    """log P_disk (eq. posterior) up to model-independent constants, and <B>.

    ``-2 log P = S^2 ff - 2 S h_f - r0^2/(2 theta^2) + 2 log theta
    - 2 log[erf(theta + r0/(2 theta)) - erf(r0/(2 theta))]``, plus the B prior's
    own normalisation so that disk and bulge populations compare correctly.
    """
    sb2 = cfg.bulge_fraction_sigma ** 2
    b0 = cfg.bulge_fraction_mean
    two_theta2 = S * S * (ff + gg - 2 * fg) + 1.0 / sb2
    theta = np.sqrt(0.5 * two_theta2)
    r0 = S * (hf - hg) + S * S * (fg - ff) - b0 / sb2
    a = theta + r0 / (2 * theta)
    b = r0 / (2 * theta)
    lediff = log_erf_diff(a, b)
    logp = (S * hf - 0.5 * S * S * ff - 0.5 * b0 * b0 / sb2 + r0 * r0 / (4 * theta * theta)
            + np.log(np.sqrt(np.pi) / 2) - np.log(theta) + lediff - log_zb)
    # <B> of the truncated Gaussian exp(-theta^2 B^2 - r0 B) on [0, 1]
    mu = -r0 / (2 * theta * theta)
    # d/dr0 log Z = -<B>;  <B> = mu + [exp(-b^2) - exp(-a^2)] / (theta sqrt(pi) [erf(a)-erf(b)])
    with np.errstate(over="ignore", invalid="ignore"):
        num = np.exp(-b * b - lediff) - np.exp(-a * a - lediff)
    meanb = np.clip(mu + num / (theta * np.sqrt(np.pi)), 0.0, 1.0)
    return logp, meanb


def _position_integral(logp_ref, logp0, g, H, tcrit, mu_min=0.0, max_step=np.inf):
    """Integral over position of exp(log P): Gaussian on a pedestal to r_max.

    log P(x) is approximated as log P0 + A exp(-x^T Q x / 2) with A the peak
    height above the pedestal and Q = -Hessian/A; the region inside r_max
    (where the height exceeds Delta chi^2_crit / 2) integrates to
    ``P0 (2 pi / sqrt(det Q)) [Ei(A) - Ei(Delta chi^2_crit / 2)]``.
    The peak value is refined from the reference position to second order.

    The second-order expansion only holds near the reference position. A
    model much longer than the galaxy (extreme ellipticity) slides along its
    major axis with almost no change in the cross-correlation, so the
    curvature there can be near zero or negative with noise, and the Newton
    step and the Gaussian volume would run away (log L up by 1e5 at one
    ellipticity). Two bounds, both continuous in the model parameters, keep
    the integral to the position prior's scale: the curvature's eigenvalues
    are raised to at least ``mu_min`` (no peak wider than the prior's radius),
    and the step to the peak is cut back along the Newton direction to at
    most ``max_step`` (the quadratic model's value at that point). The fits'
    ``max_step`` is ``position_max_step`` (a pixel), not the prior's radius:
    where the reference lies on the flank of a thin model's peak the
    quadratic, extrapolated over the radius, credited the model with up to
    34 nats above its true peak (``benchmarks/position_step.py``).
    """
    h11, h12, h22 = -H[..., 0], -H[..., 1], -H[..., 2]
    g1, g2 = g[..., 0], g[..., 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        if mu_min > 0:
            # eigen-decomposition of the 2x2 curvature, eigenvalues floored at mu_min
            half_tr = 0.5 * (h11 + h22)
            rad = np.sqrt(0.25 * (h11 - h22) ** 2 + h12 * h12)
            lam1 = np.maximum(half_tr + rad, mu_min)
            lam2 = np.maximum(half_tr - rad, mu_min)
            # squared projections of g on the eigenvectors, from the projector (M - l2 I) / (l1 - l2)
            # (no angles); with the eigenvalues (nearly) equal the split does not matter
            gg = g1 * g1 + g2 * g2
            gmg = h11 * g1 * g1 + 2 * h12 * g1 * g2 + h22 * g2 * g2
            distinct = rad > 1e-9 * np.abs(half_tr)
            p1sq = np.where(distinct, (gmg - (half_tr - rad) * gg) / np.where(distinct, 2 * rad, 1.0), gg)
            p1sq = np.clip(p1sq, 0.0, gg)
            p2sq = gg - p1sq
            ok = np.isfinite(lam1) & np.isfinite(lam2)
            logdet = np.log(lam1 * lam2)
            gqg = p1sq / lam1 + p2sq / lam2            # g^T M^-1 g
            step = np.sqrt(p1sq / lam1 ** 2 + p2sq / lam2 ** 2)
        else:
            det = h11 * h22 - h12 * h12
            ok = (h11 > 0) & (det > 0)
            logdet = np.where(ok, np.log(np.where(ok, det, 1.0)), 0.0)
            gqg = (g1 ** 2 * h22 - 2 * g1 * g2 * h12 + g2 ** 2 * h11) / det
            step = np.zeros_like(gqg)
        t = np.where(step > max_step, max_step / np.where(step > 0, step, 1.0), 1.0)
        corr = (t - 0.5 * t * t) * gqg
        corr = np.where(ok, np.maximum(corr, 0.0), 0.0)
        A = logp_ref + corr - logp0
        val = logp0 + LOG_2PI - 0.5 * logdet + np.log(np.where(A > 0, A, 1.0)) + log_ei_minus(A, tcrit)
    return np.where(ok, val, -np.inf), A, corr


@dataclass
class Marginal:
    """Log-likelihoods of models, marginalised over position and flux."""

    logl_disk: np.ndarray
    logl_bulge: np.ndarray
    mean_flux_disk: np.ndarray
    mean_flux_bulge: np.ndarray
    mean_b_disk: np.ndarray
    chi2_disk: np.ndarray      # best-fit chi^2 of the pure disk (B=0) model, minus sum y^2/sigma^2
    chi2_bulge: np.ndarray
    snr_disk: np.ndarray       # profile-weighted SNR h/sqrt(ff)
    snr_bulge: np.ndarray


SPLINE_FINE = 31   # points of the fine flux grid the spline of log P is integrated on


def _spline_logint(u, logv, n_fine=SPLINE_FINE):
    """log of the integral over u in [0, 1] of exp(cubic spline of logv(u)), per row; and the spline's argmax grid."""
    finite = np.isfinite(logv)
    rowmax = np.max(np.where(finite, logv, -np.inf), axis=1, keepdims=True)
    good_rows = np.isfinite(rowmax[:, 0])
    floor = np.where(good_rows[:, None], rowmax - 40.0, 0.0)
    lv = np.where(finite, np.maximum(logv, floor), floor)
    uf = np.linspace(u[0], u[-1], n_fine)
    vf = lv @ spline_matrix(u, uf)
    m = np.max(vf, axis=1, keepdims=True)
    w = np.exp(vf - m)
    integral = np.trapezoid(w, uf, axis=1)
    out = np.where(good_rows, m[:, 0] + np.log(integral), -np.inf)
    return out, uf, w


_INTERP_CACHE = {}


def _grid_key(kind, x, xf):
    return (kind, x.size, xf.size) + tuple(float(v) for v in x) + (float(xf[0]), float(xf[-1]))


def _uniform_pair(x, xf):
    """Whether x and xf are both uniform from x[0] to x[-1] (np.linspace): the interpolation matrices
    between them are then those of any other such pair with as many points (a spline, cubic or linear,
    commutes with an affine map of its axis), so one per (len(x), len(xf)) serves every object."""
    x = np.asarray(x, float)
    xf = np.asarray(xf, float)
    if x.size < 2 or xf.size < 2 or not x[-1] > x[0]:
        return False
    span = x[-1] - x[0]
    tol = 1e-12 * span
    return (xf[0] == x[0] and xf[-1] == x[-1]
            and np.max(np.abs(x - np.linspace(x[0], x[-1], x.size))) <= tol
            and np.max(np.abs(xf - np.linspace(x[0], x[-1], xf.size))) <= tol)


def _matrix_key(kind, x, xf):
    """The cache key of an interpolation matrix from x to xf, and the grids to make it on: a uniform pair
    (the size nodes, which move with every object) becomes the pair on [0, 1] with as many points."""
    if _uniform_pair(x, xf):
        return (kind + " uniform", len(x), len(xf)), np.linspace(0.0, 1.0, len(x)), np.linspace(0.0, 1.0, len(xf))
    return _grid_key(kind, x, xf), np.asarray(x, float), np.asarray(xf, float)


def interp_matrix(x, xf):
    """Matrix W with (values at x) @ W = linear interpolation at xf (cached per grid pair)."""
    key, x, xf = _matrix_key("linear", x, xf)
    w = _INTERP_CACHE.get(key)
    if w is None:
        w = _INTERP_CACHE[key] = np.array([np.interp(xf, x, col) for col in np.eye(x.size)])
    return w


def node_matrices(x, xf):
    """``interp_matrix(x, xf)`` and ``spline_matrix(x, xf)`` (C-contiguous, read-only, shared); where both grids
    are uniform over one span (the size nodes of a fit, which move with every object) the pair is made once per
    number of points, without a look-up of each."""
    if _uniform_pair(x, xf):
        return _uniform_node_matrices(len(x), len(xf))
    return interp_matrix(x, xf), np.ascontiguousarray(spline_matrix(x, xf))


@functools.lru_cache(maxsize=16)
def _uniform_node_matrices(n, n_fine):
    x, xf = np.linspace(0.0, 1.0, n), np.linspace(0.0, 1.0, n_fine)
    out = (interp_matrix(x, xf), np.ascontiguousarray(spline_matrix(x, xf)))
    for a in out:
        a.setflags(write=False)
    return out


def spline_matrix(x, xf):
    """Matrix W with (values at x) @ W = the not-a-knot cubic spline through them, at xf.

    A cubic spline is linear in the values it passes through, so for fixed
    nodes it is one matrix product (cached per grid pair): the same numbers
    as ``CubicSpline(x, values, axis=-1)(xf)`` without solving its system
    for every row.
    """
    key, x, xf = _matrix_key("spline", x, xf)
    w = _INTERP_CACHE.get(key)
    if w is None:
        if len(_INTERP_CACHE) > 256:   # keep the cache bounded
            _INTERP_CACHE.clear()
        w = _INTERP_CACHE[key] = CubicSpline(x, np.eye(x.size), axis=0)(xf).T.copy()
    return w


_EI_TABLE_FROM = 1.0
_EI_TABLE_STEP = 0.005


def _load_special():
    """Give the compiled marginalisation scipy.special's erfcx and expi (their cython_special C entry
    points, double versions); False where they cannot be found (the numpy path is used then)."""
    if KERNEL is None:
        return False
    # log Ei on a grid, with its derivative, for cubic interpolation (from 1, clear of Ei's root at 0.37,
    # to the asymptotic series' start)
    x = np.arange(_EI_TABLE_FROM, _EI_SERIES_FROM + 2 * _EI_TABLE_STEP, _EI_TABLE_STEP)
    ei = special.expi(x)
    table = np.ascontiguousarray(np.stack([np.log(ei), np.exp(x) / (x * ei)], axis=1))
    for c1 in special_capsules("erfcx"):
        for c2 in special_capsules("expi"):
            try:
                KERNEL.set_special(c1, c2, table, float(x[0]), _EI_TABLE_STEP)
                return True
            except ValueError:
                continue
    return False   # pragma: no cover


USE_KERNEL_MARGINAL = USE_KERNEL and _load_special()


def flux_position_marginal(sums: ModelSums, cfg: FitConfig, pixel_scale=None, use_kernel=True) -> Marginal:
    """Marginalise each model over B (disk population), position and flux.

    With ``pixel_scale`` (arcsec), the position integral is held to the
    position prior's radius, ``max_centroid_shift`` pixels (see
    :func:`_position_integral`); without it, the bare second-order integral.
    The compiled kernel computes the same numbers as the numpy code below
    (``use_kernel=False``), which stays as the reference.
    """
    marg = marginal_context(cfg, pixel_scale) if use_kernel else None
    if marg is not None:
        return _marginal_kernel(sums, marg)
    return _marginal_numpy(sums, cfg, pixel_scale)


def _log_zb(cfg):
    """log of the normalisation of the truncated-Gaussian B prior on [0, 1]."""
    return _log_zb_of(cfg.bulge_fraction_sigma, cfg.bulge_fraction_mean)


def _log_zb_of(sb, b0):
    return float(np.log(np.sqrt(np.pi / 2) * sb * (special.erf((1 - b0) / (np.sqrt(2) * sb))
                                                    - special.erf(-b0 / (np.sqrt(2) * sb)))))


def _position_bounds(cfg, pixel_scale):
    """The position integral's bounds (see :func:`_position_integral`): none without a pixel scale."""
    if pixel_scale is None:
        return {}
    mu_min, max_step = _position_limits(cfg.max_centroid_shift, cfg.position_max_step, pixel_scale)
    return dict(mu_min=mu_min, max_step=max_step)


def _position_limits(max_centroid_shift, position_max_step, pixel_scale):
    """(mu_min, max_step) of the position integral: the curvature's floor, from the position prior's radius
    (``max_centroid_shift`` pixels), and the largest step of a model's second-order move to its own peak
    (``position_max_step`` pixels, at most that radius)."""
    radius = max_centroid_shift * float(pixel_scale)
    return 1.0 / radius ** 2, min(radius, position_max_step * float(pixel_scale))


def _marginal_setup(cfg, pixel_scale):
    """The compiled marginalisation's grids, spline matrices and parameters for a configuration, cached on the
    settings they depend on (a fit calls this a few hundred times, and hashing every field of a FitConfig
    cost more than the lookup)."""
    return _marginal_setup_cached(cfg.n_flux, cfg.bulge_fraction_sigma, cfg.bulge_fraction_mean,
                                  cfg.delta_chi2_crit, cfg.max_centroid_shift, cfg.flux_prior_slope,
                                  cfg.flux_halfwidth, pixel_scale, cfg.position_max_step)


@functools.lru_cache(maxsize=32)
def _marginal_setup_cached(n_flux, sb, b0, delta_chi2_crit, max_centroid_shift, flux_prior_slope, flux_halfwidth,
                           pixel_scale, position_max_step):
    u, uf, spl, itp = _flux_grids(n_flux)
    bounded = pixel_scale is not None
    mu_min, max_step = (_position_limits(max_centroid_shift, position_max_step, pixel_scale) if bounded
                        else (0.0, np.inf))   # _position_bounds'
    par = np.array([sb ** 2, b0, _log_zb_of(sb, b0), 0.5 * delta_chi2_crit, mu_min, max_step,
                    flux_prior_slope, flux_halfwidth, 1.0 if bounded else 0.0, 0.0])
    return u, uf, spl, itp, par


@functools.lru_cache(maxsize=8)
def _flux_grids(n_flux):
    """The flux nodes, the fine grid and the spline and interpolation matrices between them (read-only): the
    part of _marginal_setup_cached that does not change with the pixel scale, which every object of distinct
    Jacobians has its own of."""
    u = np.linspace(0.0, 1.0, n_flux)
    uf = np.linspace(0.0, 1.0, SPLINE_FINE)
    for a in (u, uf):
        a.setflags(write=False)
    itp, spl = _uniform_node_matrices(n_flux, SPLINE_FINE)   # the same uniform grids over [0, 1]
    return u, uf, spl, itp


def marginal_context(cfg, pixel_scale):
    """What the compiled marginalisation takes besides the models' sums (``KERNEL.marginal``'s other arguments:
    the flux grids, their spline matrices and the parameters; ``KERNEL.size_nodes`` takes them as one tuple), or
    None where the numpy lines run instead (no compiled kernel, or ``n_flux`` beyond its range)."""
    if not (USE_KERNEL_MARGINAL and 2 <= cfg.n_flux <= 64):
        return None
    return _marginal_setup(cfg, None if pixel_scale is None else float(pixel_scale))


def _marginal_kernel(sums, marg):
    x = sums.packed()
    out = np.empty((x.shape[0], 9))
    KERNEL.marginal(x, *marg, out)
    return Marginal(logl_disk=out[:, 0], logl_bulge=out[:, 1], mean_flux_disk=out[:, 2], mean_flux_bulge=out[:, 3],
                    mean_b_disk=out[:, 4], chi2_disk=out[:, 5], chi2_bulge=out[:, 6], snr_disk=out[:, 7],
                    snr_bulge=out[:, 8])


def _marginal_numpy(sums, cfg, pixel_scale):
    nflux = cfg.n_flux
    u = np.linspace(0.0, 1.0, nflux)
    tcrit = 0.5 * cfg.delta_chi2_crit
    bounds = _position_bounds(cfg, pixel_scale)
    log_zb = _log_zb(cfg)
    out = {}
    for pop in ("disk", "bulge"):
        if pop == "disk":
            h, hh, grad, hess = sums.hf, sums.ff, sums.grad_f, sums.hess_f
        else:
            h, hh, grad, hess = sums.hg, sums.gg, sums.grad_g, sums.hess_g
        good = (hh > 0) & (h > 0)
        hh_s = np.where(good, hh, 1.0)
        s_ml = np.where(good, h / hh_s, 1.0)
        sig = 1.0 / np.sqrt(hh_s)
        lo = np.maximum(s_ml - cfg.flux_halfwidth * sig, 0.02 * s_ml)
        hi = s_ml + cfg.flux_halfwidth * sig
        S = lo[:, None] + (hi - lo)[:, None] * u[None, :]
        if pop == "disk":
            ff, gg, fg = sums.ff[:, None], sums.gg[:, None], sums.fg[:, None]
            logp, meanb = _disk_logp(S, ff, gg, fg, sums.hf[:, None], sums.hg[:, None], cfg, log_zb)
            logp0, _ = _disk_logp(S, ff, gg, fg, 0.0, 0.0, cfg, log_zb)
            g = S[..., None] * ((1 - meanb)[..., None] * sums.grad_f[:, None, :] + meanb[..., None] * sums.grad_g[:, None, :])
            H = S[..., None] * ((1 - meanb)[..., None] * sums.hess_f[:, None, :] + meanb[..., None] * sums.hess_g[:, None, :])
        else:
            logp = S * sums.hg[:, None] - 0.5 * S * S * sums.gg[:, None]
            logp0 = -0.5 * S * S * sums.gg[:, None]
            g = S[..., None] * sums.grad_g[:, None, :]
            H = S[..., None] * sums.hess_g[:, None, :]
            meanb = np.ones_like(S)
        logpos, A, corr = _position_integral(logp, logp0, g, H, tcrit, **bounds)
        logpost = logpos - cfg.flux_prior_slope * np.log(S)
        logpost = np.where(good[:, None], logpost, -np.inf)
        logint, uf, w = _spline_logint(u, logpost)
        # flux-weighted means on the fine grid (linear interpolation of S and <B> is enough there)
        Sf = lo[:, None] + (hi - lo)[:, None] * uf[None, :]
        wsum = np.sum(w, axis=1)
        wsum = np.where(wsum > 0, wsum, 1.0)
        mean_s = np.sum(w * Sf, axis=1) / wsum
        bf = meanb @ interp_matrix(u, uf) if pop == "disk" else np.ones_like(Sf)
        mean_b = np.sum(w * bf, axis=1) / wsum
        logint = logint + np.log(hi - lo)
        # best-fit chi^2 of the single-component model at its best flux and position
        gpos = grad * s_ml[:, None]
        Hpos = hess * s_ml[:, None]
        _, _, corr_ml = _position_integral(np.zeros_like(s_ml), np.zeros_like(s_ml) - 1.0, gpos, Hpos, tcrit,
                                           **bounds)
        chi2 = -(h * h / hh_s) - 2 * corr_ml
        chi2 = np.where(good, chi2, 0.0)
        snr = np.where(good, h / np.sqrt(hh_s), 0.0)
        out[pop] = (np.where(good, logint, -np.inf), mean_s, mean_b, chi2, snr)
    return Marginal(logl_disk=out["disk"][0], logl_bulge=out["bulge"][0],
                    mean_flux_disk=out["disk"][1], mean_flux_bulge=out["bulge"][1],
                    mean_b_disk=out["disk"][2], chi2_disk=out["disk"][3], chi2_bulge=out["bulge"][3],
                    snr_disk=out["disk"][4], snr_bulge=out["bulge"][4])


def coarse_peak(exposures, jacobians, disk, r_ref, half_width, step, keep=None, use_kernel=True):
    """Sky offset of the peak of the summed cross-correlation, to about a pixel.

    Each exposure's cross-correlation with a round model is one inverse FFT
    on its own pixel grid; the exposures are added on a common grid of sky
    offsets (spacing ``step`` arcsec, within +-``half_width``) by nearest
    pixel, which is all a starting point for ``find_position`` needs.
    ``keep``: per exposure, the modes to use (a mask, such as the noise-aware
    cut's ``JointModes.keep``; None: all). The compiled kernel
    (``KERNEL.coarse_modes``, ``KERNEL.coarse_gather``) makes the numpy lines' sums to rounding (numpy's
    complex product may fuse its multiply-adds) and their peak (``use_kernel=False``: the numpy lines, which
    stay as the reference).
    """
    grid = np.arange(-half_width, half_width + 0.5 * step, step)
    kernel = USE_KERNEL and use_kernel and len(disk.rho2_nodes) >= 3
    # h(s) = sum_k conj(Y) M exp(-i k.s): the inverse DFT of conj(conj(Y) M), conjugated back; the
    # exposures of one stamp shape in one inverse FFT
    hs = [None] * len(exposures)
    for (ny, nx), idx in indices_by_shape(ex.shape for ex in exposures).items():
        Cs = np.empty((len(idx), ny, nx // 2 + 1), complex)
        for slot, i in enumerate(idx):
            ex = exposures[i]
            k = None if keep is None else keep[i]
            if kernel:
                KERNEL.coarse_modes(ex.kx, ex.ky, ex.transfer, ex.coarse,
                                    b"" if k is None else np.ascontiguousarray(k, dtype=np.uint8),
                                    np.ascontiguousarray(ex.data_ft, dtype=complex), disk.rho2_nodes, disk.ft_nodes,
                                    *disk._buckets(), float(r_ref * r_ref), Cs[slot])
                continue
            if k is not None:
                ex = _select(ex, k)
            R = disk.ft_rho2(r_ref * r_ref * (ex.kx ** 2 + ex.ky ** 2))
            C = np.conj(ex.data_ft) * complex_bincount(ex.coarse, ex.transfer * R, ny * (nx // 2 + 1))
            Cs[slot] = np.conj(C.reshape(ny, nx // 2 + 1))
        for i, h in zip(idx, sfft.irfft2(Cs, s=(ny, nx))):
            hs[i] = h
    total = np.zeros((grid.size, grid.size))
    if kernel:
        for ex, J, h in zip(exposures, jacobians, hs):
            KERNEL.coarse_gather(np.ascontiguousarray(h), ex.shape[1], float(ex.sigma2), inv2(J), grid, total)
        i = divmod(int(np.argmax(total)), grid.size)
        return float(grid[i[0]]), float(grid[i[1]])
    GU, GV = np.meshgrid(grid, grid, indexing="ij")
    for ex, J, h in zip(exposures, jacobians, hs):
        ny, nx = ex.shape
        h = h / ex.sigma2
        Jinv = inv2(J)
        sx = np.rint(Jinv[0, 0] * GU + Jinv[0, 1] * GV).astype(int) % nx
        sy = np.rint(Jinv[1, 0] * GU + Jinv[1, 1] * GV).astype(int) % ny
        total += h[sy, sx]
    i = np.unravel_index(int(np.argmax(total)), total.shape)
    return float(GU[i]), float(GV[i])


def find_position(jm: JointModes, disk, r_ref, max_shift_arcsec, start=(0.0, 0.0), n_newton=8, cell=None,
                  use_kernel=True):
    """Sky offset (du, dv) of the cross-correlation peak of a round reference model.

    For centrally symmetric galaxy models the noise-free cross-correlation
    with the data peaks at the galaxy's centre whatever the model's shape or
    size (h is then symmetric about it), so one search per object serves all
    models; each model's residual offset is handled to second order later.
    Newton steps from ``start`` (see ``coarse_peak``), each at most ``cell``.
    Returns (du, dv, ok). The compiled kernel (``KERNEL.find_peak``) takes the same steps as the numpy
    lines here (``use_kernel=False``), which stay as the reference.
    """
    R = disk.ft_rho2(r_ref * r_ref * (jm.kx ** 2 + jm.ky ** 2))
    zr = jm.z * R
    cell = jm.pixel_scale if cell is None else cell
    if USE_KERNEL and use_kernel:
        c = np.ascontiguousarray
        u, v, status = KERNEL.find_peak(c(jm.kx, dtype=float), c(jm.ky, dtype=float), c(zr, dtype=complex),
                                        float(start[0]), float(start[1]), float(cell), int(n_newton))
        return float(u), float(v), status == 0 and bool(np.hypot(u, v) <= max_shift_arcsec)
    x = np.array(start, dtype=float)
    K = np.stack([jm.kx, jm.ky])
    for _ in range(n_newton):
        p = zr * np.exp(-1j * (x @ K))
        g = K @ p.imag                   # the gradient of h
        c = jm.basis @ p.real            # minus its Hessian: [kx^2, 2 kx ky, ky^2] . Re p
        try:
            step = np.linalg.solve(np.array([[c[0], 0.5 * c[1]], [0.5 * c[1], c[2]]]), g)
        except np.linalg.LinAlgError:
            return x[0], x[1], False
        if not np.all(np.isfinite(step)):
            return x[0], x[1], False
        # never step further than a pixel: Newton is only trusted near the peak
        nrm = np.hypot(*step)
        if nrm > cell:
            step *= cell / nrm
        x = x + step
        if nrm < 1e-6 * cell:
            break
    ok = bool(np.hypot(*x) <= max_shift_arcsec)
    return float(x[0]), float(x[1]), ok
