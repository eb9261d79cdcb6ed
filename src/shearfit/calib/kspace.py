"""Metacal's k-space operations in shearfit's own code.

The metacal versions of a stamp (:mod:`shearfit.calib.metacal`) are, in the
stamp's pixel frame (wavevector kappa, the sky's K = J^-T kappa for the
exposure's Jacobian J)::

    F(kappa) = I(M kappa) / P(M kappa) * Gamma(kappa),   M = J^T S J^-T

where I and P are the transforms of the stamp and of its PSF image as
interpolated images (each the pixels' discrete-time transform D times the
transform of the x-interpolant, which is the same for both since a native
PSF shares the stamp's pixels, and cancels), S the sky-frame shear of the
version and Gamma the new PSF: the PSF dilated by 1 + 2 delta,
X(d kappa) D_P(d kappa). GalSim evaluates each factor as an object of its
own, one k value at a time through its transformations; here the three
discrete transforms (the stamp, its symmetrising noise, the PSF) are taken
once per exposure on a grid padded four times (``rfft2``), and every version
interpolates them at its sheared wavevectors with one set of weights: the
quintic k-interpolant of Bernstein & Gruen (2014), the one GalSim's
``InterpolatedImage`` uses by default (and the metacal module asks for),
in the compiled loops where they are built (:func:`kvalues`).

A PSF image oversampled k times (its pixels J / k) has its own padded grid,
and its factors X and D_P are taken at kappa / k in its pixels: the
x-interpolant's transforms then no longer cancel, I = X(q) D_I(q) and
P = X(q / k) D_P(q / k) at q = M kappa.

The deconvolution is applied within the PSF's band, a disc in the sky frame
of radius ``maxk``, beyond which the product is zero, as GalSim's
``Deconvolve`` sets it beyond its PSF's maxk, where the PSF's transform
stays below ``MAXK_THRESHOLD`` of its flux (GalSim's ``maxk_threshold``):
here the radius where most of a ring's points have fallen below it
(:func:`band_edge`), within the PSF's ellipticity of GalSim's for a smooth
PSF, and not pushed out to the Nyquist radius by the scattered high
wavenumbers of a PSF model fitted from stars.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import fft as sfft

from ..engine.kernel import KERNEL, USE_KERNEL

__all__ = ["quintic", "padded_transforms", "padded_transforms_rows", "kvalues", "band_edge", "maxk_of_edge",
           "band_maxk", "round_envelope", "singular_values2", "PAD_FACTOR", "MAXK_THRESHOLD"]

#: The padded grid of the discrete transforms, in widths of the larger image (GalSim's default pad_factor).
PAD_FACTOR = 4
#: The fraction of the flux below which the PSF's transform counts as zero (GalSim's default maxk_threshold).
MAXK_THRESHOLD = 1e-3


def quintic(x):
    """The quintic interpolation kernel (Bernstein & Gruen 2014, eq. 29; GalSim's ``Quintic``): 1 at 0, 0 at
    the other integers, support \\|x\\| < 3, continuous to its second derivative."""
    x = np.abs(np.asarray(x, float))
    out = np.zeros_like(x)
    a = x <= 1
    b = (x > 1) & (x <= 2)
    c = (x > 2) & (x < 3)
    xa, xb, xc = x[a], x[b], x[c]
    out[a] = 1 + xa ** 3 * (-95 / 12 + xa * (23 / 2 + xa * (-55 / 12)))
    out[b] = (xb - 1) * (xb - 2) * (-23 / 4 + xb * (29 / 2 + xb * (-83 / 8 + xb * 55 / 24)))
    out[c] = (xc - 2) * (xc - 3) ** 2 * (-9 / 4 + xc * (25 / 12 + xc * (-11 / 24)))
    return out


def padded_size(*shapes):
    """The padded transform's size: ``PAD_FACTOR`` times the largest image side, rounded up to a fast size."""
    return sfft.next_fast_len(PAD_FACTOR * max(max(s) for s in shapes), real=True)


def _row_transforms(images, n):
    """The transforms over x of the images' rows, each zero-padded to n with its column w // 2 at index 0 (the
    columns left of it at the grid's end): (len(images), largest height, n // 2 + 1) complex."""
    ny = max(im.shape[0] for im in images)
    rows = np.zeros((len(images), ny, n))
    for t, im in enumerate(images):
        h, w = im.shape
        if h > n or w > n:
            raise ValueError(f"an image of {h} x {w} pixels does not fit a padded grid of {n}")
        c = w // 2
        rows[t, :h, :w - c] = im[:, c:]
        rows[t, :h, n - c:] = im[:, :c]
    return sfft.rfft(rows, axis=2, workers=1)


def padded_transforms(images, n):
    """The discrete-time transforms of real images, each about its pixel (ny // 2, nx // 2), sampled on the
    n x n grid of wavevectors 2 pi (i, j) / n (pixel units): an array (len(images), n // 2 + 1, n) complex,
    image, then kx >= 0 (the others by Hermitian symmetry), then ky, as the transpose of ``rfft2`` of each
    image zero-padded to n and rolled so that its origin pixel is at index 0."""
    # the transform over x of the images' rows only (the padding's rows are zero), then over y (the last
    # axis, contiguous)
    part = _row_transforms(images, n)
    cols = np.zeros((len(images), n // 2 + 1, n), complex)
    for t, im in enumerate(images):
        _place_columns(cols[t], part[t], im.shape[0], n, 0)
    return sfft.fft(cols, axis=2, workers=1, overwrite_x=True)


#: What :func:`padded_transform_within` leaves in the columns it does not make: None, the memory as it was (tests set
#: NaN: a read of one then shows in every result it reaches).
UNMADE = None


def padded_transform_within(image, n, columns, xkernel, threshold=MAXK_THRESHOLD):
    """:func:`padded_transforms` of one image (``(1, n // 2 + 1, n)``), made only at the columns kx = 0 .. m - 1 (all
    their ky), m at least ``columns``; the others hold :data:`UNMADE`. m is ``columns`` where every wavevector beyond
    is proven to lie below the band's threshold (:func:`band_maxk`'s test, ``xkernel`` its x-interpolant): each column
    beyond is the transform over y of the rows' transforms at its kx, so its values are at most the sum of their
    moduli there, which is compared with the threshold (with a margin far above the transforms' rounding); where a
    column fails, m reaches past it. The columns made are the whole table's to the bit (each column's transform is
    its own), so that :func:`band_edge` of the first m rows is the whole table's, and a
    read of the first m rows is its read. Returns (table, m).

    (A PSF image oversampled k times, as a PSFEx or Piff model gives one at each object, has a table k times the
    stamp's, of which metacal's bands read about the first third of the columns, :func:`shearfit.calib.metacal`: its
    transform was half of the images' time.)"""
    part = _row_transforms([image], n)[0]
    nc = n // 2 + 1
    m = min(max(int(columns), 1), nc)
    if m < nc:
        # |T(kx, ky)| <= sum_j |part[j, kx]|, against threshold |T(0, 0)| (the sum of column 0, with a margin for
        # the transforms' rounding, ~1e-15 of these sums)
        bound = np.abs(part[:, m:]).sum(axis=0) * _band_xmax(n, xkernel)[m:] * (1 + 1e-6)
        thr = threshold * abs(part[:, 0].sum()) * (1 - 1e-6)
        over = np.nonzero(bound > thr)[0]
        if over.size:
            m = m + int(over[-1]) + 1
    # (the columns not made left as the memory was, unless a test asks for UNMADE: never read, and never touched, so
    # that their pages are not faulted in; zeroing the whole table cost as much as the transform)
    table = np.empty((1, nc, n), complex) if UNMADE is None else np.full((1, nc, n), UNMADE, complex)
    _column_transforms(part, image.shape[0], n, table[0, :m], 0)
    return table, m


def padded_transform_rest(image, table, m):
    """A table of :func:`padded_transform_within` (of ``image``, made at its first m columns) made whole in place:
    its columns from m on, the same numbers as :func:`padded_transforms`' (the columns made before untouched). The
    table must be writeable."""
    n = table.shape[2]
    if m < n // 2 + 1:
        _column_transforms(_row_transforms([image], n)[0], image.shape[0], n, table[0, m:], m)


def _place_columns(cols, part, h, n, lo):
    """Into ``cols`` (rows of a table, zero: kx = lo, lo + 1, ...), the rows' transforms ``part`` ((>= h, n // 2 + 1):
    an image of h rows, each transformed over x) at those kx, as columns over ky, the image's row h // 2 at index 0
    (the rows above it at the grid's end)."""
    c = h // 2
    hi = lo + cols.shape[0]
    cols[:, :h - c] = part[c:h, lo:hi].T
    cols[:, n - c:] = part[:c, lo:hi].T


def _column_transforms(part, h, n, cols, lo):
    """Into ``cols`` (rows of a table, in place: kx = lo, lo + 1, ...), the transforms over y of the rows'
    transforms ``part`` (:func:`_place_columns`) at those kx."""
    cols[:] = 0.0
    _place_columns(cols, part, h, n, lo)
    got = sfft.fft(cols, axis=1, workers=1, overwrite_x=True)
    if not np.shares_memory(got, cols):
        cols[:] = got


def padded_transforms_rows(images, n):
    """:func:`padded_transforms` in rows: an array (n, n // 2 + 1, len(images)) complex, ky, then kx >= 0, then the
    image (``rfft2``'s own order, the images innermost), so that a wavevector's taps along kx and its values for every
    image are adjacent in memory (metacal's compiled band for a PSF grid k times the stamp's). The same values, to
    the transforms' rounding. Two float64 images of one shape are laid out and placed by the compiled loops
    (``padded_rows``, ``padded_place``: the same arrays as the numpy lines)."""
    if (USE_KERNEL and len(images) == 2 and images[0].shape == images[1].shape
            and all(im.dtype == np.float64 for im in images) and max(images[0].shape) <= n):
        h, w = images[0].shape
        rows = np.empty((2, h, n))
        KERNEL.padded_rows(np.ascontiguousarray(images[0]), np.ascontiguousarray(images[1]), h, w, n, rows)
        out = np.empty((n, n // 2 + 1, 2), complex)
        KERNEL.padded_place(sfft.rfft(rows, axis=2, workers=1), h, n, out)
        return sfft.fft(out, axis=0, workers=1, overwrite_x=True)
    part = _row_transforms(images, n)
    out = np.zeros((n, n // 2 + 1, len(images)), complex)
    for t, im in enumerate(images):
        h = im.shape[0]
        c = h // 2
        out[:h - c, :, t] = part[t, c:h]
        out[n - c:, :, t] = part[t, :c]
    return sfft.fft(out, axis=0, workers=1, overwrite_x=True)


def _taps(p):
    """The six table indices around positions p (floor(p) - 2 .. floor(p) + 3) and their quintic weights."""
    f0 = np.floor(p)
    idx = f0[:, None].astype(np.int64) + np.arange(-2, 4)[None, :]
    return idx, quintic(p[:, None] - idx)


def kvalues_numpy(table, tx, ty):
    """:func:`kvalues` in numpy (the reference for the compiled loop, and the fallback without it)."""
    n = table.shape[2]
    ix, wx = _taps(np.asarray(tx, float))
    iy, wy = _taps(np.asarray(ty, float))
    ix = ix % n
    iy = iy % n
    out = np.zeros((ix.shape[0], table.shape[0]), complex)
    for b in range(6):
        for a in range(6):
            cx, cy = ix[:, a], iy[:, b]
            low = cx <= n // 2
            rows = np.where(low, cy, (n - cy) % n)
            cols = np.where(low, cx, n - cx)
            v = table[:, cols, rows].T
            v = np.where(low[:, None], v, np.conj(v))
            out += (wy[:, b] * wx[:, a])[:, None] * v
    return out


def kvalues(table, tx, ty):
    """The transforms of ``table`` (:func:`padded_transforms`) at the wavevectors (tx, ty), in units of the
    table's step 2 pi / n, by quintic interpolation (6 x 6 taps, periodic, Hermitian): (len(tx), ntab)
    complex. One set of weights serves every image of the table."""
    tx = np.ascontiguousarray(tx, dtype=float)
    ty = np.ascontiguousarray(ty, dtype=float)
    if not USE_KERNEL:
        return kvalues_numpy(table, tx, ty)
    table = np.ascontiguousarray(table, dtype=complex)
    out = np.empty((tx.size, table.shape[0]), complex)
    KERNEL.quintic_kvalues(table, int(table.shape[2]), int(table.shape[0]), tx, ty, out)
    return out


def band_edge(psf_column, xkernel, threshold=MAXK_THRESHOLD):
    """The PSF's band in its image's own pixel frame: the radius 2 pi b / n of the first ring b of the padded grid
    (its wavevectors kappa with b <= \\|kappa\\| n / (2 pi) < b + 1, rings one grid step wide about the origin) in
    which at most half of the points carry a transform (``psf_column``, (n // 2 + 1, n): kx, then ky, times the
    x-interpolant's transform ``xkernel(kappa_x) xkernel(kappa_y)``) above ``threshold`` of its flux; the grid's
    outermost radius where no ring is such, 0 where the origin's is. The PSF's transform falls below the threshold
    at this radius in most directions: a PSF image with noise of its own (a pixel model fitted from stars, as
    PSFEx, Piff and shearfit's own give) lifts scattered points above it far beyond, out to the pixels' Nyquist
    radius, which would set the band there if any one point did (GalSim's ``calculate_maxk`` test), and the band
    there deconvolves those points' noise into every version (``benchmarks/README.md``, session 97). It depends on
    the image alone: :func:`maxk_of_edge` gives the sky band for a Jacobian. ``psf_column`` may be the table's
    first rows alone (:func:`padded_transform_within`'s columns made, beyond which no point is above)."""
    n = psf_column.shape[1]
    rows = psf_column.shape[0]
    total = _ring_totals(n)
    thr = threshold * abs(psf_column[0, 0])
    xx = _band_grid(n, xkernel)[2][:rows]   # (the table's first rows alone: see above)
    above = None
    if USE_KERNEL and psf_column.dtype == np.complex128 and psf_column.flags.c_contiguous:
        # compiled (``band_rings``): the test on squares from tables of xx^2 and of the rings, the points within
        # rounding of the threshold taken back for numpy's test below (the same counts; in metacal's run 42 against
        # 73 us an exposure of a 48-pixel stamp, session 98)
        xx2, labels = _ring_tables(n, xkernel)
        above = np.empty(total.size, np.int64)
        near = np.empty(256, np.int64)
        got = KERNEL.band_rings(psf_column, xx2, labels, float(thr), above, near)
        if got > 0:
            q = near[:got]
            col = psf_column.ravel()[q]
            keep = np.abs(col) * xx.ravel()[q] > thr
            np.add.at(above, labels.ravel()[q][keep], 1)
        elif got < 0:
            above = None
    if above is None:
        above = np.bincount(_ring_labels(n)[:rows][np.abs(psf_column) * xx > thr], minlength=total.size)
    fail = np.nonzero(2 * above <= total)[0]
    return 2 * np.pi * (int(fail[0]) if fail.size else total.size) / n


def maxk_of_edge(edge, jac, smax=None):
    """The sky radius of the PSF's band for the Jacobian ``jac`` (of the PSF image's pixels) from its
    :func:`band_edge`: the largest sky disc whose wavevectors kappa = J^T K in the pixel frame lie within that radius,
    and within the pixels' Nyquist disc pi, beyond which a stamp's transform only repeats itself: min(edge, pi) /
    s_max, s_max the Jacobian's larger singular value (``smax``, where the caller has it already)."""
    return float(min(edge, np.pi) / (singular_values2(jac)[0] if smax is None else smax))


def band_maxk(psf_column, xkernel, jac, threshold=MAXK_THRESHOLD, smax=None):
    """The sky radius of the PSF's band (:func:`maxk_of_edge` of :func:`band_edge`; ``psf_column`` as that takes
    it, ``smax`` as the former)."""
    return maxk_of_edge(band_edge(psf_column, xkernel, threshold), jac, smax)


@functools.lru_cache(maxsize=8)
def _ring_labels(n):
    """Each point's ring on the padded grid (:func:`band_edge`'s): floor(sqrt(i^2 + m^2)), i the kx index, m = min(j,
    n - j) of the ky index j ((n // 2 + 1, n) int64, read-only, shared)."""
    i = np.arange(n // 2 + 1)[:, None]
    j = np.arange(n)
    m = np.minimum(j, n - j)[None, :]
    lab = np.sqrt((i * i + m * m).astype(float)).astype(np.int64)
    lab.setflags(write=False)
    return lab


@functools.lru_cache(maxsize=8)
def _ring_tables(n, xkernel):
    """:func:`band_edge`'s tables for the compiled count: xx^2 of :func:`_band_grid` and the rings of
    :func:`_ring_labels` as int32, both (n // 2 + 1, n), C-contiguous, read-only, shared."""
    xx2 = np.ascontiguousarray(_band_grid(n, xkernel)[2] ** 2)
    labels = np.ascontiguousarray(_ring_labels(n), dtype=np.int32)
    for a in (xx2, labels):
        a.setflags(write=False)
    return xx2, labels


@functools.lru_cache(maxsize=8)
def _ring_totals(n):
    """The number of the padded grid's points in each of :func:`band_edge`'s rings (read-only, shared)."""
    out = np.bincount(_ring_labels(n).ravel())
    out.setflags(write=False)
    return out


def round_envelope(psf_column, xkernel, jac, dilation, maxk):
    """A round new PSF for metacal (its ``psf='round'``): as a function of the sky wavenumber \\|K\\|, the least over
    directions of the dilated PSF's \\|transform\\| (``psf_column`` as :func:`band_maxk` takes it, times the
    x-interpolant's transform), made non-increasing in \\|K\\|, and 0 beyond the dilated band ``maxk / dilation``.

    The dilated PSF's transform at K is the PSF's at ``dilation K``, so each point kappa of the padded grid,
    of sky wavevector J^-T kappa, gives the dilated PSF's \\|transform\\| at \\|J^-T kappa\\| / dilation. These are
    taken in bins one grid step wide in \\|K\\| (the step along the Jacobian's longer sky axis), the least of each
    bin, then the running least outwards. The result lies below the dilated PSF's \\|transform\\| in every
    direction (to the interpolation between the bins), so that dividing by the sheared PSF and multiplying by it
    amplifies nothing more than the dilated PSF does, and it is a function of \\|K\\| alone: a round PSF on the
    sky, whose images carry no PSF anisotropy into the ellipticities. Returns (knots, values) in \\|K\\|
    (values[0] = 1 at K = 0; 0 from the last knot on), for an interpolation that stays between each knot's
    value and the next's (linear in \\|K\\|, or in \\|K\\|^2 as :func:`shearfit.calib.metacal.round_psf` takes it,
    smooth at K = 0)."""
    n = psf_column.shape[1]
    kx, ky, xx = _band_grid(n, xkernel)
    amp = np.abs(psf_column) * xx
    amp /= amp[0, 0]   # the flux: 1 at K = 0
    jac = np.asarray(jac, float)
    a, b, c = _inverse_form(jac)
    ksky = np.sqrt(np.maximum(a * kx * kx + 2 * b * kx * ky + c * ky * ky, 0.0)) / dilation
    edge = maxk / dilation
    step = 2 * np.pi / n / singular_values2(jac)[0]   # the grid's step in sky |K| along its longer axis
    nbin = int(edge / step) + 1   # bins from i step, i = 0 .. nbin - 1, all below or at the band's edge
    # (the band's edge may be the norm of one of the grid's wavevectors, as the bands' own test takes it: inside
    # however rounding computes the two norms)
    inside = ksky <= edge * (1 + 1e-12)
    which = np.minimum((ksky[inside] / step).astype(np.int64), nbin - 1)
    least = np.full(nbin, np.inf)
    np.minimum.at(least, which, amp[inside])
    least[0] = 1.0   # at K = 0 (the bin's other points lie above the chord from there to the next bin's least)
    least = np.minimum(np.minimum.accumulate(least), 1.0)
    # each bin's least at its lower edge (the envelope is non-increasing, so the bin's points lie at or beyond
    # it; between two edges the interpolation stays below both), then zero beyond the band
    knots = step * np.arange(nbin)
    values = least
    if knots[-1] < edge:
        knots, values = np.append(knots, edge), np.append(values, least[-1])
    return np.append(knots, edge * (1 + 1e-9)), np.append(values, 0.0)


def _inverse_form(jac):
    """(a, b, c): \\|J^-T kappa\\|^2 = a kx^2 + 2 b kx ky + c ky^2, the quadratic form of (J^T J)^-1 = adj(J^T J) /
    det(J)^2."""
    (p, q), (r, s) = jac
    det2 = (p * s - q * r) ** 2
    return (q * q + s * s) / det2, -(p * q + r * s) / det2, (p * p + r * r) / det2


def singular_values2(A):
    """The larger and the smaller singular value of a 2 x 2 matrix (closed form)."""
    # (on Python floats, numpy's hypot: the same numbers as on numpy's scalars, a fifth of the overhead)
    (a, b), (c, d) = np.asarray(A, float).tolist()
    p = a * a + b * b + c * c + d * d
    q = float(np.hypot(a * a + b * b - c * c - d * d, 2 * (a * c + b * d)))
    return math.sqrt(0.5 * (p + q)), math.sqrt(max(0.5 * (p - q), 0.0))


@functools.lru_cache(maxsize=8)
def _band_xmax(n, xkernel):
    """The largest of :func:`_band_grid`'s \\|X(kx) X(ky)\\| at each kx (read-only, shared)."""
    out = _band_grid(n, xkernel)[2].max(axis=1)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=8)
def _band_grid(n, xkernel):
    """The padded grid's wavevectors, kx (n // 2 + 1, 1) and ky (1, n), and |X(kx) X(ky)| there, X the
    x-interpolant's transform (read-only, shared)."""
    ky = 2 * np.pi * sfft.fftfreq(n)
    kx = 2 * np.pi * np.arange(n // 2 + 1) / n
    xx = np.abs(xkernel(kx))[:, None] * np.abs(xkernel(ky))[None, :]
    out = kx[:, None], ky[None, :], xx
    for a in out:
        a.setflags(write=False)
    return out
