"""Postage stamps: finding an object on the CCDs of the exposures and cutting it out.

Following the paper (sec. 3.6 and 4, "image combination"), a stamp is cut
from each exposure around the integer pixel nearest the object's catalogue
position, with no interpolation of the data, and the sub-pixel remainder is
handed to the model as the :class:`~shearfit.Observation`'s ``offset``.
Interpolating would correlate the pixel noise and distort the PSF, which the
method avoids by fitting each exposure's own pixels.

Coordinates are numpy's: ``image[y, x]``, pixel centres at integer indices,
so a CCD's pixel area is ``-0.5 <= x < nx - 0.5``, ``-0.5 <= y < ny - 0.5``.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ShearfitValueError

__all__ = ["Stamp", "cut_stamp", "Locations", "locate_all", "locate"]


class Stamp(NamedTuple):
    """A postage stamp and where it came from; unpacks as ``(image, weight, offset, bounds)``.

    Attributes
    ----------
    image : 2D float64 array
        Counts; 0 outside the CCD and where the CCD's pixel is not finite.
    weight : 2D float64 array
        Inverse variance; 0 outside the CCD and at non-finite pixels.
    offset : (dx, dy)
        The object's position minus the stamp centre, pixels (the
        Observation's ``offset``); each in [-0.5, 0.5].
    bounds : (y0, y1, x0, x1)
        The CCD pixels the stamp spans, half-open (``image[y0:y1, x0:x1]``
        of the CCD); may extend past the CCD's edges.
    """

    image: np.ndarray
    weight: np.ndarray
    offset: tuple
    bounds: tuple

    @property
    def centre(self) -> tuple:
        """CCD pixel ``(iy, ix)`` at the stamp's centre index ``(ny // 2, nx // 2)``."""
        return (self.bounds[0] + self.image.shape[0] // 2, self.bounds[2] + self.image.shape[1] // 2)


def _on_ccd(x, y, shape):
    ny, nx = shape
    return (x >= -0.5) & (x < nx - 0.5) & (y >= -0.5) & (y < ny - 0.5)


def cut_stamp(image: np.ndarray, weight, x: float, y: float, size: int) -> Optional[Stamp]:
    """Cut a ``size`` x ``size`` stamp around position ``(x, y)`` of a CCD, without interpolation.

    Parameters
    ----------
    image : 2D array
        The CCD's pixels (may be a read-only memory map; it is not changed).
    weight : 2D array of ``image``'s shape, or float
        Inverse variance per pixel, or one constant value for the whole CCD.
    x, y : float
        The object's position, 0-based pixel coordinates, ``x`` along columns.
    size : int
        Side of the stamp, pixels.

    Returns
    -------
    Stamp or None
        None if ``(x, y)`` lies outside the CCD's pixel area (or is not
        finite). Otherwise the stamp centred on the pixel
        ``(iy, ix) = (floor(y + 1/2), floor(x + 1/2))`` nearest the object,
        which sits at index ``(size // 2, size // 2)``; ``offset = (x - ix,
        y - iy)``. Stamp pixels off the CCD have value and weight 0, as do
        pixels whose value is NaN or infinite.
    """
    size = int(size)
    if size < 1:
        raise ShearfitValueError(f"stamp size must be a positive number of pixels, got {size}")
    if image.ndim != 2:
        raise ShearfitValueError(f"cut_stamp needs a 2D image, got shape {image.shape}")
    scalar_weight = np.ndim(weight) == 0
    if scalar_weight:
        if weight is None or not (np.isfinite(weight) and weight >= 0):
            raise ShearfitValueError(f"cut_stamp needs a non-negative weight, got {weight!r}")
    elif np.shape(weight) != image.shape:
        raise ShearfitValueError(f"weight shape {np.shape(weight)} differs from image shape {image.shape}")
    x = float(x)
    y = float(y)
    if not (np.isfinite(x) and np.isfinite(y)) or not _on_ccd(x, y, image.shape):
        return None

    ny, nx = image.shape
    # floor(v + 1/2) rather than np.rint: rint rounds halves to even, which would make
    # the stamp of an object at x = 10.5 and one at 11.5 shift by different amounts.
    ix = int(np.floor(x + 0.5))
    iy = int(np.floor(y + 0.5))
    half = size // 2
    y0, x0 = iy - half, ix - half
    y1, x1 = y0 + size, x0 + size
    # The part of the stamp that lies on the CCD.
    cy0, cy1 = max(y0, 0), min(y1, ny)
    cx0, cx1 = max(x0, 0), min(x1, nx)

    stamp = np.zeros((size, size), dtype=np.float64)
    wstamp = np.zeros((size, size), dtype=np.float64)
    inner = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    stamp[inner] = image[cy0:cy1, cx0:cx1]
    if scalar_weight:
        wstamp[inner] = float(weight)
    else:
        wstamp[inner] = weight[cy0:cy1, cx0:cx1]
    # A NaN times a zero weight is still NaN in a chi^2; the value must go too.
    bad = ~np.isfinite(stamp)
    if bad.any():
        stamp[bad] = 0.0
        wstamp[bad] = 0.0
    return Stamp(stamp, wstamp, (x - ix, y - iy), (y0, y1, x0, x1))


# --- locating objects on CCDs ------------------------------------------------------------

class Locations(NamedTuple):
    """Every (object, CCD) pair where the object lies on the CCD, sorted by object then CCD.

    ``object`` indexes the input positions, ``ccd`` the CCD list; ``x``,
    ``y`` are the object's 0-based pixel coordinates on that CCD.
    """

    object: np.ndarray
    ccd: np.ndarray
    x: np.ndarray
    y: np.ndarray


def _unit_vectors(ra_deg, dec_deg) -> np.ndarray:
    ra = np.radians(ra_deg)
    dec = np.radians(dec_deg)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def _lonlat_axes(wcs):
    """Which world axis is longitude: world_to_pixel takes axes in the WCS's own order."""
    wcs.wcs.set()  # lng is only known once wcsprm is set up; a WCS built in code may not be yet
    lng = wcs.wcs.lng
    return (0, 1) if lng in (0, -1) else (1, 0)


def _pix2world(wcs, x, y):
    out = wcs.all_pix2world(np.asarray(x, float), np.asarray(y, float), 0)
    i, j = _lonlat_axes(wcs)
    return out[i], out[j]


def _world2pix(wcs, ra, dec):
    i, _ = _lonlat_axes(wcs)
    world = (ra, dec) if i == 0 else (dec, ra)
    # all_world2pix with origin 0 is world_to_pixel_values, including SIP/TPV distortion; quiet=True
    # returns its best solution instead of raising where the distortion polynomial fails to invert
    # (far off the chip), and such points fail the pixel-area test anyway.
    x, y = wcs.all_world2pix(np.asarray(world[0], float), np.asarray(world[1], float), 0, quiet=True)
    return np.asarray(x, float), np.asarray(y, float)


def _footprint_cap(wcs, shape, n_edge: int = 16):
    """A spherical cap (centre unit vector, radius in radians) that contains a CCD.

    The CCD outline is sampled along its edges; the cap reaches the farthest
    sample plus a margin for the bulge of a distorted edge between samples.
    A cap rather than an (ra, dec) box needs no care at ra = 0/360 or the poles.
    """
    ny, nx = shape
    t = np.linspace(0.0, 1.0, n_edge + 1)
    xs = np.concatenate([-0.5 + t * nx, np.full_like(t, nx - 0.5), nx - 0.5 - t * nx, np.full_like(t, -0.5)])
    ys = np.concatenate([np.full_like(t, -0.5), -0.5 + t * ny, np.full_like(t, ny - 0.5), ny - 0.5 - t * ny])
    ra_c, dec_c = _pix2world(wcs, [(nx - 1) / 2.0], [(ny - 1) / 2.0])
    ra_e, dec_e = _pix2world(wcs, xs, ys)
    centre = _unit_vectors(ra_c, dec_c)[0]
    edge = _unit_vectors(ra_e, dec_e)
    if not (np.all(np.isfinite(centre)) and np.all(np.isfinite(edge))):
        return np.array([0.0, 0.0, 1.0]), np.pi  # the WCS cannot say: test every object exactly
    radius = float(np.max(np.arccos(np.clip(edge @ centre, -1.0, 1.0))))
    return centre, min(np.pi, 1.02 * radius + 1e-7)


def _shape_of(ccd):
    shape = getattr(ccd, "shape", None)
    if shape is None:
        shape = ccd.image.shape
    return tuple(shape)


def locate_all(ccds: Sequence, ra, dec) -> Locations:
    """Find every CCD each object lies on.

    Parameters
    ----------
    ccds : sequence
        Objects with ``wcs`` (celestial :class:`astropy.wcs.WCS`) and
        ``shape`` (ny, nx), such as :class:`~shearfit.io.fits.ExposureCCD`.
    ra, dec : float or array
        Object positions, degrees.

    Returns
    -------
    Locations
        One entry per (object, CCD) pair whose pixel area holds the object,
        sorted by object and then CCD. Objects on no CCD do not appear.

    Notes
    -----
    A k-d tree of the objects' unit vectors finds, for each CCD, the objects
    inside a cap that contains it; only those go through the WCS, so the
    cost is about (objects + objects on CCDs), not objects x CCDs.
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    if ra.shape != dec.shape or ra.ndim != 1:
        raise ShearfitValueError(f"ra and dec must be 1D arrays of one shape, got {ra.shape} and {dec.shape}")
    finite = np.flatnonzero(np.isfinite(ra) & np.isfinite(dec))
    found_obj, found_ccd, found_x, found_y = [], [], [], []
    tree = cKDTree(_unit_vectors(ra[finite], dec[finite])) if finite.size else None
    for k, ccd in enumerate(ccds):
        if tree is None:
            break
        shape = _shape_of(ccd)
        centre, radius = _footprint_cap(ccd.wcs, shape)
        chord = 2.0 * np.sin(radius / 2.0)
        cand = finite[np.asarray(tree.query_ball_point(centre, chord), dtype=np.intp)]
        if cand.size == 0:
            continue
        x, y = _world2pix(ccd.wcs, ra[cand], dec[cand])
        inside = _on_ccd(x, y, shape)
        found_obj.append(cand[inside])
        found_ccd.append(np.full(int(inside.sum()), k, dtype=np.intp))
        found_x.append(x[inside])
        found_y.append(y[inside])
    if not found_obj:
        empty = np.zeros(0)
        return Locations(empty.astype(np.intp), empty.astype(np.intp), empty, empty)
    obj = np.concatenate(found_obj)
    ccd_idx = np.concatenate(found_ccd)
    order = np.lexsort((ccd_idx, obj))
    return Locations(obj[order], ccd_idx[order], np.concatenate(found_x)[order], np.concatenate(found_y)[order])


def locate(ccds: Sequence, ra, dec):
    """The CCDs that an object (or each of many objects) lies on.

    Parameters
    ----------
    ccds : sequence
        As for :func:`locate_all`.
    ra, dec : float or 1D array
        Degrees.

    Returns
    -------
    list
        For scalar ``ra``, ``dec``: a list of ``(ccd_index, x, y)``, one per
        CCD whose pixel area contains the object (empty if none). For arrays:
        one such list per object, in input order.
    """
    scalar = np.ndim(ra) == 0 and np.ndim(dec) == 0
    loc = locate_all(ccds, ra, dec)
    n = 1 if scalar else len(np.atleast_1d(ra))
    starts = np.searchsorted(loc.object, np.arange(n + 1))
    out = [[(int(loc.ccd[j]), float(loc.x[j]), float(loc.y[j])) for j in range(starts[i], starts[i + 1])]
           for i in range(n)]
    return out[0] if scalar else out
