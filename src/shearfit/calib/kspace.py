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
of radius ``maxk`` (the largest sky wavenumber where the PSF's transform
exceeds ``MAXK_THRESHOLD`` of its flux, GalSim's ``maxk_threshold``),
beyond which the product is zero, as GalSim's ``Deconvolve`` sets it.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import fft as sfft

from ..engine.kernel import KERNEL, USE_KERNEL

__all__ = ["quintic", "padded_transforms", "padded_transforms_rows", "kvalues", "band_maxk", "band_points",
           "band_maxk_of_points", "round_envelope", "singular_values2", "PAD_FACTOR", "MAXK_THRESHOLD"]

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
    its own), so that :func:`band_maxk` and :func:`band_points` of the first m rows are the whole table's, and a
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


def band_maxk(psf_column, xkernel, jac, threshold=MAXK_THRESHOLD):
    """The sky radius of the PSF's band: the largest norm of J^-T kappa over the padded grid's wavevectors kappa
    where the PSF's transform (``psf_column``, (n // 2 + 1, n): kx, then ky, times the x-interpolant's transform
    ``xkernel(kappa_x) xkernel(kappa_y)``) exceeds ``threshold`` of its flux, and at most pi / s_max (s_max the
    largest singular value of the Jacobian ``jac``): the largest sky disc whose wavevectors stay within the
    pixels' Nyquist square, beyond which a stamp's transform only repeats itself. ``psf_column`` may be the table's
    first rows alone (:func:`padded_transform_within`'s columns made, beyond which no point is above)."""
    n = psf_column.shape[1]
    kx, ky, xx = _band_grid(n, xkernel)
    kx, xx = kx[:psf_column.shape[0]], xx[:psf_column.shape[0]]   # (the table's first rows alone: see above)
    thr = threshold * abs(psf_column[0, 0])
    jac = np.asarray(jac, float)
    nyquist = np.pi / singular_values2(jac)[0]
    a, b, c = _inverse_form(jac)
    if USE_KERNEL and psf_column.dtype == np.complex128 and psf_column.flags.c_contiguous:
        # the same loop compiled (the same value to the bit, in a tenth of the time)
        k2max = KERNEL.band_maxk(psf_column, xx, kx, ky, float(thr), float(a), float(b), float(c))
    else:
        above = np.abs(psf_column) * xx > thr
        k2 = a * kx * kx + 2 * b * kx * ky + c * ky * ky
        # (the largest over the band by a select, not a boolean index: the same value in a quarter of the time)
        k2max = np.max(np.where(above, k2, -np.inf))
    if k2max == -np.inf:
        return 0.0
    return float(min(np.sqrt(k2max), nyquist))


def band_points(psf_column, xkernel, threshold=MAXK_THRESHOLD):
    """The wavevectors (kx, ky) of the padded grid where the PSF's transform exceeds ``threshold`` of its flux
    (:func:`band_maxk`'s points), reduced to the vertices of their convex hull: the largest of a positive definite
    quadratic form over the points, which :func:`band_maxk_of_points` takes for a Jacobian, lies at a vertex, so
    that a PSF image's band is found for any Jacobian from a few points. (2, m), or (2, 0) where no point is above.
    ``psf_column`` may be the table's first rows alone, as :func:`band_maxk` takes it."""
    from scipy.spatial import ConvexHull, QhullError

    n = psf_column.shape[1]
    kx, ky, xx = _band_grid(n, xkernel)
    kx, xx = kx[:psf_column.shape[0]], xx[:psf_column.shape[0]]   # (the table's first rows alone: see above)
    thr = threshold * abs(psf_column[0, 0])
    if USE_KERNEL and psf_column.dtype == np.complex128 and psf_column.flags.c_contiguous:
        # each ky's least and largest kx above (compiled, band_maxk's test): the hull's vertices are among them,
        # and the hull of these few points is made in a tenth of the time of all of them
        ext = np.empty((n, 2), np.int64)
        KERNEL.band_extent(psf_column, xx, float(thr), ext)
        j = np.nonzero(ext[:, 0] >= 0)[0]
        above = (ext[j].T.ravel(), np.tile(j, 2))
    else:
        above = np.nonzero(np.abs(psf_column) * xx > thr)
    pts = np.stack([kx[above[0], 0], ky[0, above[1]]])
    if pts.shape[1] >= 3:
        try:
            pts = pts[:, ConvexHull(pts.T).vertices]
        except QhullError:   # collinear points: all of them
            pass
    return np.ascontiguousarray(pts)


def band_maxk_of_points(points, jac):
    """:func:`band_maxk` from :func:`band_points`' points: the largest \\|J^-T kappa\\| over them, at most pi / s_max."""
    jac = np.asarray(jac, float).tolist()   # (on Python floats: the same numbers, less overhead)
    nyquist = np.pi / singular_values2(jac)[0]
    if points.shape[1] == 0:
        return 0.0
    a, b, c = _inverse_form(jac)
    kx, ky = points
    return float(min(math.sqrt((a * kx * kx + 2 * b * kx * ky + c * ky * ky).max()), nyquist))


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
    inside = ksky <= edge
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
