"""Reading a field's files and writing the shear catalogue.

Formats are those of docs/interface.rst ("Input: a field", "Output: the shear
catalogue"). Every error is one line naming the file and, where it applies,
the HDU, column or header keyword, so that the command line can print it as
it is.

Image and weight arrays are memory-mapped where FITS allows it (unscaled
data): a field of tens of exposures of tens of CCDs would not fit in memory,
and only the postage stamps are ever needed from it. Tile-compressed HDUs
(``fpack``, ``.fits.fz``) and scaled integers (``BSCALE``/``BZERO``) cannot
be mapped as they lie on disk: their pixels are read on demand instead, only
the part a stamp or a block of rows asks for, decompressed and scaled to
float (:class:`HDUPixels`), which bounds memory the same way.
"""

from __future__ import annotations

import json
import logging
import mmap
import os
import re
import uuid
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, NamedTuple, Optional

import numpy as np
from astropy.io import fits
from astropy.stats import mad_std, sigma_clip
from astropy.table import Column, MaskedColumn, Table
from astropy.wcs import WCS, FITSFixedWarning

from ..errors import (FITCLASS_FIT_FAILED, ShearfitError, ShearfitIOError, ShearfitKeyError,
                      ShearfitValueError)

__all__ = [
    "COMMON_ZEROPOINT",
    "ExposureCCD",
    "HDUPixels",
    "OutputColumn",
    "metacal_columns",
    "read_catalog",
    "bad_rows",
    "read_exposure",
    "detached",
    "attach_pixels",
    "release_pages",
    "estimate_noise",
    "photometric_scale",
    "write_catalog_atomic",
    "provenance_cards",
    "output_columns",
    "empty_result_row",
    "empty_output_table",
]

logger = logging.getLogger(__name__)

#: AB zero point of the common flux unit: ``model_flux`` is in counts at this zero point (docs/interface.rst).
COMMON_ZEROPOINT = 30.0

CATALOG_COLUMNS = ("id", "ra", "dec", "mag")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _open_fits(path: str, memmap: bool):
    if not os.path.exists(path):
        raise ShearfitIOError(f"{path}: no such file")
    if os.path.isdir(path):
        raise ShearfitIOError(f"{path}: is a directory, not a FITS file")
    try:
        hdul = fits.open(path, memmap=memmap)
        # Parsing every header now makes a truncated file fail here, with its name, not later.
        len(hdul)
    except Exception as exc:  # astropy raises OSError, ValueError or IndexError depending on the damage
        raise ShearfitIOError(f"{path}: not a readable FITS file ({_first_line(exc)})") from None
    return hdul


def _hdu_label(path: str, index: int, hdu) -> str:
    name = hdu.header.get("EXTNAME", "PRIMARY" if index == 0 else "")
    return f"{path}, HDU {index}" + (f" ({str(name).strip()})" if name else "")


# --- catalogues -----------------------------------------------------------------------

def read_catalog(path, strict: bool = True) -> Table:
    """Read an object (or star) catalogue.

    Parameters
    ----------
    path : str or os.PathLike
        A FITS file; the first table HDU is read.
    strict : bool
        With False, rows whose ``ra`` or ``dec`` is not finite (NaN, inf or
        masked) or whose ``dec`` lies outside [-90, 90] are kept (as NaN or
        as they are) instead of failing the read: the field pipeline gives
        such rows, and rows without a finite ``mag``, fitclass -7
        (:func:`bad_rows` finds them).

    Returns
    -------
    astropy.table.Table
        In the file's row order, with the columns ``id``, ``ra``, ``dec``
        (degrees) and ``mag`` renamed to lower case (they are matched without
        regard to case), ``ra``, ``dec`` and ``mag`` as float64; other columns
        are kept as they are.

    Raises
    ------
    ShearfitIOError
        The file is missing or not FITS.
    ShearfitKeyError
        A required column is missing.
    ShearfitValueError
        No table HDU, an empty table, non-finite or out-of-range ``ra`` or
        ``dec`` (``strict`` only), duplicate ``id`` values (the message lists
        them), or two columns differing only in case.
    """
    path = os.fspath(path)
    # Catalogues are small next to images; reading them into memory lets the file be closed at once.
    with _open_fits(path, memmap=False) as hdul:
        index = next((i for i, h in enumerate(hdul) if isinstance(h, (fits.BinTableHDU, fits.TableHDU))), None)
        if index is None:
            kinds = ", ".join(f"{i}:{type(h).__name__}" for i, h in enumerate(hdul))
            raise ShearfitValueError(f"{path}: no table HDU in the file (HDUs: {kinds})")
        where = _hdu_label(path, index, hdul[index])
        try:
            with warnings.catch_warnings():
                # Non-standard unit strings are common in survey catalogues and harmless here.
                warnings.simplefilter("ignore")
                table = Table.read(hdul[index])
        except Exception as exc:
            raise ShearfitValueError(f"{where}: cannot read the table ({_first_line(exc)})") from None

    by_lower: dict = {}
    for name in table.colnames:
        by_lower.setdefault(name.lower(), []).append(name)
    for req in CATALOG_COLUMNS:
        names = by_lower.get(req, [])
        if not names:
            raise ShearfitKeyError(f"{where}: catalogue has no column {req!r} (matched without regard to case; "
                                   f"columns: {', '.join(table.colnames)})")
        if len(names) > 1:
            raise ShearfitValueError(f"{where}: columns {', '.join(map(repr, names))} all match {req!r}; "
                                     f"keep one")
        if table[names[0]].ndim != 1:
            raise ShearfitValueError(f"{where}: column {names[0]!r} must hold one value per row, "
                                     f"has shape {table[names[0]].shape[1:]} per row")
        if names[0] != req:
            table.rename_column(names[0], req)

    if len(table) == 0:
        raise ShearfitValueError(f"{where}: the catalogue is empty")

    for name in ("ra", "dec", "mag"):
        col = table[name]
        if col.dtype.kind not in "biuf":
            raise ShearfitValueError(f"{where}: column {name!r} must be numeric, has type {col.dtype}")
        values = np.ma.filled(np.ma.asarray(col).astype(np.float64), np.nan)
        table[name] = Column(values, name=name, unit=col.unit, description=col.description)
    for name in ("ra", "dec"):
        bad = np.flatnonzero(~np.isfinite(table[name]))
        if bad.size and strict:
            raise ShearfitValueError(f"{where}: column {name!r} is not finite (NaN, inf or masked) in "
                                     f"{bad.size} rows, the first row {bad[0]}")
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(np.abs(table["dec"]) > 90)
    if bad.size and strict:
        raise ShearfitValueError(f"{where}: column 'dec' lies outside [-90, 90] degrees in {bad.size} rows, "
                                 f"the first row {bad[0]} (dec={table['dec'][bad[0]]})")

    ids = table["id"]
    if isinstance(ids, MaskedColumn) and np.any(ids.mask):
        raise ShearfitValueError(f"{where}: column 'id' has masked (null) values, "
                                 f"the first row {np.flatnonzero(ids.mask)[0]}")
    ids = np.asarray(ids)
    _, first, counts = np.unique(ids, return_index=True, return_counts=True)
    if np.any(counts > 1):
        # Name the duplicate that occurs first in the file: that is where a user will look; then the others.
        firsts = np.sort(first[counts > 1])
        dup_first = firsts[0]
        again = np.flatnonzero(ids == ids[dup_first])[1]

        def _value(i):
            v = ids[i].item()
            return v.decode(errors="replace") if isinstance(v, bytes) else v

        more = ""
        if firsts.size > 1:
            shown = ", ".join(repr(_value(i)) for i in firsts[:10]) + (", ..." if firsts.size > 10 else "")
            more = f"; {firsts.size} ids occur more than once: {shown}"
        raise ShearfitValueError(f"{where}: duplicate id {_value(dup_first)!r} in column 'id' "
                                 f"(rows {dup_first} and {again}){more}; ids must be unique")
    return table


def bad_rows(catalog: Table) -> dict:
    """Rows of a catalogue read with ``strict=False`` that cannot be measured, by column.

    Returns
    -------
    dict
        ``{"ra": rows, "dec": rows, "mag": rows}``: the rows (indices, in
        file order) whose value is NaN, infinite or masked, for ``dec`` also
        outside [-90, 90] degrees. A row may appear under several columns.
    """
    out = {}
    for name in ("ra", "dec", "mag"):
        values = np.asarray(catalog[name], dtype=np.float64)
        bad = ~np.isfinite(values)
        if name == "dec":
            with np.errstate(invalid="ignore"):
                bad |= np.abs(values) > 90
        out[name] = np.flatnonzero(bad)
    return out


# --- exposures ------------------------------------------------------------------------

@dataclass(eq=False)
class ExposureCCD:
    """One CCD of one exposure: pixels, weights, WCS and photometric keywords.

    Attributes
    ----------
    image : 2D array, HDUPixels or None
        Background-subtracted counts, read-only: memory-mapped where the file
        allows, else (a tile-compressed or scaled-integer HDU) an
        :class:`HDUPixels` that reads what is sliced from it. May hold
        NaN/inf where the file does: :func:`cut_stamp` gives them weight 0.
        None in a :func:`detached` copy.
    weight : 2D array, HDUPixels or None
        Inverse variance per pixel, counts^-2, 0 for unusable pixels
        (memory-mapped, or as ``image``). None when no weight file was given:
        then :attr:`noise_ivar` holds everywhere.
    wcs : astropy.wcs.WCS
        The celestial WCS of the CCD.
    magzp, gain, saturate : float
        Header keywords ``MAGZP`` (AB zero point of the counts), ``GAIN``
        (e-/ADU) and ``SATURATE`` (ADU).
    path : str
        The image file.
    hdu : int
        Index of the CCD's HDU in the image file.
    extname : str
        Its ``EXTNAME`` ('' if none).
    weight_path : str or None
        The weight file, if one was given.
    noise_ivar : float or None
        The constant inverse variance estimated from the image when no
        weight file was given.
    n_bad_pixels : int
        NaN/inf image pixels whose weight was set to 0.
    header : astropy.io.fits.Header
        The CCD's header (for keywords later steps may want).
    dims : tuple
        (ny, nx), which :attr:`shape` gives also when the pixels are detached.
    weight_hdu : int or None
        Index of the CCD's HDU in the weight file.
    usable : bool
        False where the CCD has no usable pixel (every weight 0, every pixel
        NaN, or no weight file and no scatter to estimate the noise from):
        the field pipeline leaves it out.
    ccd_index : int
        Position of the CCD among the image file's CCD HDUs (0-based): the
        given PSF's HDU that belongs to it. Equals the position in the list
        :func:`read_exposure` returns unless CCDs without a WCS were left out.
    n_file_ccds : int
        CCD HDUs in the image file, left-out ones included.
    """

    image: np.ndarray = field(repr=False)
    weight: Optional[np.ndarray] = field(repr=False)
    wcs: WCS = field(repr=False)
    magzp: float
    gain: float
    saturate: float
    path: str
    hdu: int
    extname: str = ""
    weight_path: Optional[str] = None
    noise_ivar: Optional[float] = None
    n_bad_pixels: int = 0
    header: Optional[fits.Header] = field(default=None, repr=False)
    dims: tuple = ()
    weight_hdu: Optional[int] = None
    usable: bool = True
    ccd_index: int = 0
    n_file_ccds: int = 1

    @property
    def shape(self) -> tuple:
        return tuple(self.dims) if self.image is None else self.image.shape

    @property
    def pixel_weight(self):
        """The weight array, or the constant inverse variance where there is none (for :func:`cut_stamp`)."""
        return self.weight if self.weight is not None else self.noise_ivar

    @property
    def flux_scale(self) -> float:
        """Counts in this exposure per unit of the common flux (zero point 30)."""
        return photometric_scale(self.magzp)

    @property
    def label(self) -> str:
        return f"{self.path}, HDU {self.hdu}" + (f" ({self.extname})" if self.extname else "")


def _memmappable(hdu) -> bool:
    """Whether astropy can memory-map the HDU's pixels as they lie on disk (no compression, no scaling)."""
    if isinstance(hdu, fits.CompImageHDU):
        return False
    h = hdu.header
    if h.get("BSCALE", 1) != 1 or h.get("BZERO", 0) != 0:
        return False
    return not (h.get("BITPIX", -32) > 0 and "BLANK" in h)


class HDUPixels:
    """The pixels of a tile-compressed or scaled-integer image HDU, read where they are sliced.

    Such HDUs cannot be memory-mapped: the bytes on disk are not the values.
    Reading the whole CCD into memory for every chunk of objects would undo
    what the memory maps bound, so this reads, through astropy's
    ``section``, only the rows (scaled integers) or tiles (compressed) that
    hold the slice asked for, decompressed and scaled to float (float32 for
    ``BITPIX`` 8, 16 and -32, else float64), and keeps nothing but an open
    file handle. Slicing returns a read-only numpy array, as a memory map's
    read-only view would; ``np.asarray`` reads the whole image.

    Parameters
    ----------
    path : str
        The FITS file.
    index : int
        The HDU's index in it.
    shape : tuple
        (ny, nx).
    bitpix : int
        The image's ``BITPIX`` (for a compressed HDU, that of the image it holds).
    """

    ndim = 2

    def __init__(self, path: str, index: int, shape, bitpix: int):
        self.path = path
        self.index = int(index)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(np.float32 if int(bitpix) in (8, 16, -32) else np.float64)
        self._hdul = None

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self):
        return f"HDUPixels({self.path!r}, HDU {self.index}, shape={self.shape}, dtype={self.dtype})"

    def _section(self):
        if self._hdul is None:
            # no memory map: astropy cannot map these HDUs, and a section read through a file handle keeps nothing
            self._hdul = fits.open(self.path, memmap=False)
        return self._hdul[self.index].section

    def close(self) -> None:
        """Close the file handle (it opens again at the next read)."""
        if self._hdul is not None:
            self._hdul.close()
            self._hdul = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_hdul"] = None
        return state

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        if any(k is Ellipsis for k in key):
            i = next(j for j, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (2 - len(key) + 1) + key[i + 1:]
        if len(key) > 2:
            raise IndexError(f"too many indices for a 2D image: {len(key)}")
        key = key + (slice(None),) * (2 - len(key))
        box, sub, scalar, simple = [], [], [], True
        for k, n in zip(key, self.shape):
            if isinstance(k, slice):
                start, stop, step = k.indices(n)
                if step == 1:
                    stop = max(stop, start)
                    box.append(slice(start, stop))
                    sub.append(np.arange(stop - start))
                    scalar.append(False)
                    continue
                idx = np.arange(start, stop, step)
                scalar.append(False)
            elif isinstance(k, (int, np.integer)) and not isinstance(k, bool):
                i = int(k) + (n if int(k) < 0 else 0)
                if not 0 <= i < n:
                    raise IndexError(f"index {int(k)} is out of bounds for axis of size {n}")
                idx = np.array([i])
                scalar.append(True)
            else:
                raise TypeError(f"HDUPixels takes integers and slices, not {type(k).__name__}")
            simple = False
            lo = int(idx.min()) if idx.size else 0
            hi = int(idx.max()) + 1 if idx.size else 0
            box.append(slice(lo, hi))
            sub.append(idx - lo)
        if any(b.stop <= b.start for b in box):
            out = np.zeros(tuple(len(s) for s, sc in zip(sub, scalar) if not sc), dtype=self.dtype)
        else:
            try:
                data = np.asarray(self._section()[tuple(box)], dtype=self.dtype)
            except (OSError, ValueError, TypeError, IndexError) as exc:
                raise ShearfitIOError(f"{self.path}, HDU {self.index}: cannot read the pixels "
                                      f"({_first_line(exc)})") from None
            out = data if simple else data[np.ix_(*sub)]
            if any(scalar):
                out = out[tuple(0 if sc else slice(None) for sc in scalar)]
        if isinstance(out, np.ndarray) and out.ndim:
            out.flags.writeable = False
        return out

    def __array__(self, dtype=None, copy=None):
        out = np.array(self[:, :])
        return out if dtype is None else out.astype(dtype, copy=False)


def _pixels(hdul, path: str, index: int, label: str):
    """The pixels of HDU ``index``: memory-mapped where the HDU allows, else an :class:`HDUPixels`."""
    hdu = hdul[index]
    if not _memmappable(hdu):
        return HDUPixels(path, index, hdu.shape, hdu.header.get("BITPIX", -32))
    try:
        return _readonly(hdu.data)
    except Exception as exc:
        raise ShearfitIOError(f"{label}: cannot read the pixels ({_first_line(exc)})") from None


def _ccd_indices(hdul) -> list:
    """The CCD HDUs: the primary if it holds data, else every image extension that does."""
    primary = hdul[0]
    if primary.header.get("NAXIS", 0) > 0:
        return [0]
    return [i for i, h in enumerate(hdul) if i > 0 and getattr(h, "is_image", False)
            and h.header.get("NAXIS", 0) > 0]


def _keyword(hdul, index: int, key: str, label: str) -> float:
    header = hdul[index].header
    # Multi-extension files often keep exposure-wide keywords in the primary header
    # (the FITS INHERIT convention), so look there too.
    if key not in header and index > 0 and key in hdul[0].header:
        header = hdul[0].header
    if key not in header:
        raise ShearfitKeyError(f"{label}: header keyword {key} is missing")
    value = header[key]
    try:
        if isinstance(value, bool):
            raise TypeError
        value = float(value)
    except (TypeError, ValueError):
        raise ShearfitValueError(f"{label}: header keyword {key}={header[key]!r} is not a number") from None
    if not np.isfinite(value):
        raise ShearfitValueError(f"{label}: header keyword {key}={value!r} is not finite")
    if key in ("GAIN", "SATURATE") and not value > 0:
        raise ShearfitValueError(f"{label}: header keyword {key}={value!r} must be positive")
    return value


def _read_wcs(hdul, index: int, label: str) -> WCS:
    header = hdul[index].header
    try:
        with warnings.catch_warnings():
            # astropy "fixes" harmless non-standard keywords (DATE-OBS formats, RADECSYS) with a warning.
            warnings.simplefilter("ignore", FITSFixedWarning)
            wcs = WCS(header, fobj=hdul, relax=True)
    except Exception as exc:
        raise ShearfitValueError(f"{label}: the WCS cannot be read by astropy ({_first_line(exc)})") from None
    if not wcs.has_celestial:
        ctypes = ", ".join(f"{k}={header[k]!r}" for k in ("CTYPE1", "CTYPE2") if k in header) or "no CTYPE1/2"
        raise ShearfitValueError(f"{label}: no celestial WCS in the header ({ctypes})")
    if wcs.naxis != 2:
        wcs = wcs.celestial
    ny, nx = hdul[index].shape
    try:
        world = wcs.all_pix2world([[(nx - 1) / 2.0, (ny - 1) / 2.0]], 0)
    except Exception as exc:
        raise ShearfitValueError(f"{label}: the WCS fails at the CCD centre ({_first_line(exc)})") from None
    if not np.all(np.isfinite(world)):
        raise ShearfitValueError(f"{label}: the WCS gives no sky position at the CCD centre")
    return wcs


def _readonly(a: np.ndarray) -> np.ndarray:
    view = a.view()
    view.flags.writeable = False
    return view


def estimate_noise(image: np.ndarray, max_pixels: int = 1_000_000) -> float:
    """Robust standard deviation of the pixel noise of a background-subtracted image.

    The median absolute deviation, scaled to a Gaussian sigma, of the pixels
    left after iterative 4-sigma clipping, which removes objects. Exactly
    zero pixels of a floating-point image are left out: they mark regions
    without data (chip gaps, masks), and would pull the MAD down.

    Parameters
    ----------
    image : 2D array
    max_pixels : int
        Whole rows are taken at a regular stride until about this many pixels
        are used: the noise is the same everywhere, and a full CCD would take
        seconds.

    Returns
    -------
    float
        Sigma in the image's units; 0 or NaN if the image has no scatter.
    """
    stride = max(1, int(np.ceil(image.size / max_pixels)))
    sample = np.asarray(image[::stride], dtype=np.float64).ravel()
    keep = np.isfinite(sample)
    if image.dtype.kind == "f":
        keep &= sample != 0
    sample = sample[keep]
    if sample.size < 10:
        return float("nan")
    # Clipping at 4 rather than 3 sigma: clipping cuts the Gaussian's tails, which lowers the MAD
    # of what is left (by 0.3 % at 3 sigma, 0.005 % at 4); objects still go.
    clipped = sigma_clip(sample, sigma=4.0, maxiters=10, cenfunc="median", stdfunc="mad_std", masked=False)
    return float(mad_std(clipped))


def read_exposure(image_path, weight_path=None, skip_unusable: bool = False) -> list:
    """Read one exposure: every CCD's pixels, weights, WCS and keywords.

    Parameters
    ----------
    image_path : str or os.PathLike
        FITS file; each CCD is one image HDU (the primary if it has data,
        else each image extension: for a tile-compressed ``.fits.fz`` file,
        the compressed extensions). Each CCD header needs a celestial WCS and
        the keywords ``MAGZP``, ``GAIN`` and ``SATURATE`` (looked up in the
        primary header too). Pixels may be floats or scaled integers
        (``BSCALE``/``BZERO``), compressed or not.
    weight_path : str or os.PathLike, optional
        FITS file of inverse variances with the same HDU layout and shapes.
        Without it a constant inverse variance per CCD is estimated from the
        image (:func:`estimate_noise`) and logged.
    skip_unusable : bool
        What the field pipeline asks for: a CCD without a usable WCS (none,
        not celestial, unreadable, or failing at the CCD centre) is left out
        of the list with a warning naming its file and HDU, instead of
        failing the read; a CCD without a usable pixel (every weight 0, every
        pixel NaN, or no weight file and no scatter) is returned with
        ``usable=False`` and a warning (without ``skip_unusable`` such a CCD
        is returned marked too, with no warning, and one without scatter
        fails as before).

    Returns
    -------
    list of ExposureCCD
        One per CCD, in file order.

    Raises
    ------
    ShearfitIOError
        A file is missing or not FITS.
    ShearfitKeyError
        A required header keyword is missing.
    ShearfitValueError
        No image HDU, a non-2D image, an unreadable or non-celestial WCS
        (unless ``skip_unusable``), a weight file whose layout or shapes
        differ, negative, NaN or infinite weights, or an image whose noise
        cannot be estimated (unless ``skip_unusable``).
    """
    image_path = os.fspath(image_path)
    weight_path = None if weight_path is None else os.fspath(weight_path)
    hdul = _open_fits(image_path, memmap=True)
    whdul = None
    # the pixel checks read row blocks through handles without a memory map, so that a scan of every
    # pixel leaves nothing resident: the maps above only ever hold the pages that stamps touch
    scan = _open_fits(image_path, memmap=False)
    wscan = None
    try:
        indices = _ccd_indices(hdul)
        if not indices:
            raise ShearfitValueError(f"{image_path}: no image HDU with data")
        windices = None
        if weight_path is not None:
            whdul = _open_fits(weight_path, memmap=True)
            wscan = _open_fits(weight_path, memmap=False)
            windices = _ccd_indices(whdul)
            if len(windices) != len(indices):
                raise ShearfitValueError(
                    f"{weight_path} has {len(windices)} image HDUs but {image_path} has {len(indices)}; "
                    f"the weight file must have the image's HDU layout")

        ccds = []
        estimated = []
        for k, index in enumerate(indices):
            hdu = hdul[index]
            label = _hdu_label(image_path, index, hdu)
            if hdu.header.get("NAXIS") != 2:
                raise ShearfitValueError(f"{label}: the image must be 2D, has NAXIS={hdu.header.get('NAXIS')}")
            magzp = _keyword(hdul, index, "MAGZP", label)
            gain = _keyword(hdul, index, "GAIN", label)
            saturate = _keyword(hdul, index, "SATURATE", label)
            try:
                wcs = _read_wcs(hdul, index, label)
            except ShearfitValueError as exc:
                if not skip_unusable:
                    raise
                logger.warning("%s; the CCD is left out", exc)
                continue
            image = _pixels(hdul, image_path, index, label)
            n_bad, = _scan_blocks(scan[index], label, [lambda b: ~np.isfinite(b)])
            unusable = "every pixel is NaN or infinite" if n_bad == image.size else None

            weight = None
            noise_ivar = None
            windex = None
            if whdul is not None:
                windex = windices[k]
                whdu = whdul[windex]
                wlabel = _hdu_label(weight_path, windex, whdu)
                if whdu.shape != hdu.shape:
                    raise ShearfitValueError(f"{wlabel} has shape {whdu.shape} but {label} has {hdu.shape}; "
                                             f"the weight file must match the image")
                weight = _pixels(whdul, weight_path, windex, wlabel)
                # NaN fails ">= 0", so this one test catches NaN, negative and infinite weights.
                n_invalid, n_positive = _scan_blocks(wscan[windex], wlabel,
                                                     [lambda b: ~((b >= 0) & (b < np.inf)), lambda b: b > 0])
                if n_invalid:
                    raise ShearfitValueError(
                        f"{wlabel}: {n_invalid} weights are negative, NaN or infinite; weights are inverse "
                        f"variances, 0 for unusable pixels")
                if n_positive == 0:
                    unusable = unusable or f"every weight in {wlabel} is 0"
            else:
                sigma = estimate_noise(image)
                if np.isfinite(sigma) and sigma > 0:
                    noise_ivar = 1.0 / sigma**2
                    estimated.append(f"HDU {index} sigma={sigma:.4g}")
                elif skip_unusable:
                    # weight 0 everywhere: stamps and star cuts see no usable pixel
                    noise_ivar = 0.0
                    unusable = unusable or "no weight file and no scatter in the image to estimate the noise from"
                else:
                    raise ShearfitValueError(f"{label}: cannot estimate the noise without a weight file: "
                                             f"the image has no scatter")
            if unusable and skip_unusable:
                logger.warning("%s: %s; the CCD is left out", label, unusable)
            elif n_bad:
                logger.warning("%s: %d NaN or infinite pixels; their weight is set to 0", label, n_bad)

            ccds.append(ExposureCCD(
                image=image, weight=weight,
                wcs=wcs, magzp=magzp, gain=gain, saturate=saturate,
                path=image_path, hdu=index, extname=str(hdu.header.get("EXTNAME", "")).strip(),
                weight_path=weight_path, noise_ivar=noise_ivar, n_bad_pixels=n_bad,
                header=hdu.header.copy(), dims=tuple(hdu.shape), weight_hdu=windex,
                usable=unusable is None, ccd_index=k, n_file_ccds=len(indices),
            ))
        if weight_path is None and estimated:
            logger.info("%s: no weight file; a constant noise per CCD was estimated from the image "
                        "(sigma-clipped MAD): %s", image_path, ", ".join(estimated))
        return ccds
    finally:
        # Closing keeps memory-mapped arrays valid: astropy leaves the map open while they are referenced.
        for h in (hdul, whdul, scan, wscan):
            if h is not None:
                h.close()


def _scan_blocks(hdu, label, tests, rows=256) -> list:
    """For each function in ``tests``, the pixels where ``test(block)`` holds, read in blocks of ``rows`` rows.

    Nothing is kept in memory; each block is read once for all the tests. ``hdu.section`` reads
    plain, scaled and tile-compressed images alike (a handle opened without a memory map).
    """
    n = [0] * len(tests)
    try:
        for y0 in range(0, hdu.shape[0], rows):
            block = hdu.section[y0:y0 + rows, :]
            for i, test in enumerate(tests):
                n[i] += int(np.count_nonzero(test(block)))
    except (OSError, ValueError, TypeError, IndexError) as exc:
        raise ShearfitIOError(f"{label}: cannot read the pixels ({_first_line(exc)})") from None
    return n


def detached(ccds) -> list:
    """The CCDs without their pixels and WCS (keywords, shape, file and HDU): cheap to send to workers.

    The WCS goes too: astropy pickles a WCS through a header written with
    fewer digits than it holds (1e-14 relative), which would make a worker's
    catalogue differ from a single process's. :func:`attach_pixels` reads it
    again from the file, as :func:`read_exposure` did.
    """
    return [replace(c, image=None, weight=None, wcs=None, dims=c.shape) for c in ccds]


def release_pages(ccds) -> None:
    """Drop the memory-mapped pages read so far from this process's resident memory.

    They stay in the operating system's file cache, so reading them again is
    cheap; the process's own memory then holds no more than the stamps of
    the object in hand, however many objects it has measured. Pixels read on
    demand (:class:`HDUPixels`: compressed or scaled HDUs) hold no pages and
    are passed over.
    """
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:
        return
    seen = set()
    for c in ccds:
        for a in (c.image, c.weight):
            while a is not None and not isinstance(a, mmap.mmap):
                a = getattr(a, "base", None)
            if a is not None and id(a) not in seen:
                seen.add(id(a))
                try:
                    a.madvise(advice)
                except (OSError, ValueError):
                    pass


#: The WCS that :func:`attach_pixels` read, by (file, HDU, the file's size and modification time): a process
#: that measures several chunks of a field parses each CCD's WCS once (astropy's parse of a TPV or SIP header
#: takes milliseconds a CCD). The WCS objects are only read from.
_ATTACHED_WCS: dict = {}


def _attached_wcs(hdul, path, index: int, label: str) -> WCS:
    st = os.stat(path)
    key = (os.path.realpath(path), int(index), st.st_size, st.st_mtime_ns)
    wcs = _ATTACHED_WCS.get(key)
    if wcs is None:
        if len(_ATTACHED_WCS) >= 1024:
            _ATTACHED_WCS.clear()
        wcs = _ATTACHED_WCS[key] = _read_wcs(hdul, index, label)
    return wcs


def attach_pixels(ccds) -> list:
    """:func:`detached` CCDs with their pixels memory-mapped again (files already checked by :func:`read_exposure`).

    The maps close when the returned CCDs are dropped, and with them the
    pages read: a worker that attaches per chunk holds only that chunk's.
    Compressed or scaled HDUs get an :class:`HDUPixels` again, as in
    :func:`read_exposure`.
    The WCS is read from the image header as :func:`read_exposure` reads it.
    """
    handles = {}
    try:
        out = []
        for c in ccds:
            for path in (c.path, c.weight_path):
                if path is not None and path not in handles:
                    handles[path] = _open_fits(path, memmap=True)
            image = _pixels(handles[c.path], c.path, c.hdu, c.label)
            weight = None
            if c.weight_path is not None:
                weight = _pixels(handles[c.weight_path], c.weight_path, c.weight_hdu,
                                 _hdu_label(c.weight_path, c.weight_hdu, handles[c.weight_path][c.weight_hdu]))
            wcs = _attached_wcs(handles[c.path], c.path, c.hdu, c.label)
            out.append(replace(c, image=image, weight=weight, wcs=wcs))
        return out
    finally:
        for h in handles.values():
            h.close()


def photometric_scale(magzp, common_zp: float = COMMON_ZEROPOINT):
    """Counts in an exposure per unit of the common flux.

    A source of magnitude m gives ``10**(-0.4 (m - magzp))`` counts and has
    common flux ``10**(-0.4 (m - common_zp))`` (docs/interface.rst: ``model_flux`` is
    for an AB zero point of 30), so the ratio is

    .. math:: s = 10^{0.4\\,(\\mathrm{magzp} - \\mathrm{zp}_{\\rm common})}.

    Parameters
    ----------
    magzp : float or array
        AB zero point of the exposure's counts.
    common_zp : float
        Zero point of the common flux.
    """
    scale = 10.0 ** (0.4 * (np.asarray(magzp, dtype=np.float64) - common_zp))
    return float(scale) if scale.ndim == 0 else scale


# --- output ---------------------------------------------------------------------------

class OutputColumn(NamedTuple):
    """One column of the shear catalogue."""

    name: str
    dtype: str
    unit: str
    description: str


_OUTPUT_COLUMNS = (
    OutputColumn("id", "i8", "", "object id, from the input catalogue"),
    OutputColumn("ra", "f8", "deg", "right ascension, from the input catalogue"),
    OutputColumn("dec", "f8", "deg", "declination, from the input catalogue"),
    OutputColumn("mag", "f8", "mag", "AB magnitude, from the input catalogue"),
    OutputColumn("e1", "f8", "", "ellipticity, un-calibrated; (u, v) frame, +u west, +v north; e1>0 east-west"),
    OutputColumn("e2", "f8", "", "ellipticity, un-calibrated; (u, v) frame, +u west, +v north"),
    OutputColumn("weight", "f8", "", "inverse-variance lensing weight (eq. weight); 0 where not measured"),
    OutputColumn("e_var", "f8", "", "1D variance of the likelihood surface in ellipticity"),
    OutputColumn("fitclass", "i2", "", "0 galaxy, 1 star, <0 not measured (see shearfit.errors)"),
    OutputColumn("snr", "f8", "", "profile-weighted signal-to-noise ratio over the exposures"),
    OutputColumn("scalelength", "f8", "arcsec", "likelihood-weighted semi-major-axis disk scalelength"),
    OutputColumn("bulge_fraction", "f8", "", "posterior mean bulge-to-total flux ratio"),
    OutputColumn("model_flux", "f8", "", "posterior mean total flux, counts at AB zero point 30"),
    OutputColumn("n_exposures_used", "i2", "", "exposures that entered the joint fit"),
    OutputColumn("psf_e1", "f8", "", "mean PSF model ellipticity at the object, (u, v) frame"),
    OutputColumn("psf_e2", "f8", "", "mean PSF model ellipticity at the object, (u, v) frame"),
    OutputColumn("psf_fwhm", "f8", "arcsec", "mean PSF FWHM at the object (adaptive moments, 2.3548 sigma)"),
    OutputColumn("m", "f8", "", "multiplicative calibration m(snr, scalelength; psf_fwhm for a resolution table)"),
    OutputColumn("star_pvalue", "f8", "", "F-test probability that the galaxy model's improvement over a point "
                                          "source is chance (sec. 3.2); large for stars"),
    OutputColumn("stamp_size", "i2", "pix", "side of the stamps the object was measured on (larger than "
                                            "stamp_size where its model needed it); 0 where none was cut"),
    OutputColumn("flux_snr", "f8", "", "SNR of model_flux were the object a point source (its shape does "
                                       "not enter: a shear leaves it unchanged)"),
    OutputColumn("round_scalelength", "f8", "arcsec", "likelihood mean of the round scalelength of the same "
                                                      "area, r sqrt(q) (a shear changes it far less than "
                                                      "scalelength)"),
    OutputColumn("iso_weight", "f8", "", "lensfit's weight made isotropic: the mean weight of the catalogue's "
                                         "galaxies in the object's bin of flux_snr; "
                                         "a shear leaves it unchanged; 0 where not a measured galaxy"),
)


#: Quantities kept from each sheared metacal version (column ``name_1p`` etc.).
METACAL_QUANTITIES = (("e1", "f8", ""), ("e2", "f8", ""), ("weight", "f8", ""), ("snr", "f8", ""),
                      ("scalelength", "f8", "arcsec"), ("fitclass", "i2", ""))


def metacal_columns() -> list:
    """The extra columns of a metacal catalogue (``calibration: metacal``; the contract's terms).

    For each sheared version v in 1p, 1m, 2p, 2m (shear +-delta in component
    1 or 2, applied in the (u, v) frame) the fit's ``e1_v``, ``e2_v``,
    ``weight_v``, ``snr_v``, ``scalelength_v``, ``fitclass_v``; and the
    per-galaxy response ``Rij = (e_i[j+] - e_i[j-]) / (2 delta)``. The
    catalogue's own ``e1``, ``e2``, ``weight``, ... are the ``noshear``
    version's (the stamps deconvolved and reconvolved with the dilated PSF,
    no shear).
    """
    cols = []
    for v in ("1p", "1m", "2p", "2m"):
        for q, dt, unit in METACAL_QUANTITIES:
            cols.append(OutputColumn(f"{q}_{v}", dt, unit, f"metacal {v} version: {q}"))
    for i in (1, 2):
        for j in (1, 2):
            cols.append(OutputColumn(f"R{i}{j}", "f8", "", f"metacal shear response de{i}/dg{j}"))
    return cols


def output_columns(include_input: bool = True) -> list:
    """The shear catalogue's columns (docs/interface.rst), in order.

    Parameters
    ----------
    include_input : bool
        Include ``id``, ``ra``, ``dec``, ``mag``, which are copied from the
        input catalogue (``id`` keeps the input's type there).

    Returns
    -------
    list of OutputColumn
        ``(name, dtype, unit, description)``.
    """
    return [c for c in _OUTPUT_COLUMNS if include_input or c.name not in CATALOG_COLUMNS]


def empty_result_row(fitclass: int = FITCLASS_FIT_FAILED) -> dict:
    """The measurement columns of an object not (yet) measured.

    Floats are NaN except ``weight``, which is 0 (docs/interface.rst: "0 where not
    measured"); ``n_exposures_used`` is 0. The input columns are not included:
    they are copied from the catalogue.
    """
    row = {}
    for c in output_columns(include_input=False):
        row[c.name] = np.nan if c.dtype.startswith("f") else 0
    row["weight"] = 0.0
    row["iso_weight"] = 0.0
    row["fitclass"] = int(fitclass)
    return row


def empty_output_table(catalog: Table, fitclass: int = FITCLASS_FIT_FAILED, metacal: bool = False) -> Table:
    """A shear catalogue for ``catalog``, in its order, with every object unmeasured.

    The pipeline fills rows in as objects are fitted; ``id``, ``ra``,
    ``dec`` and ``mag`` are copied from ``catalog``. ``metacal`` adds
    :func:`metacal_columns`.
    """
    out = Table()
    n = len(catalog)
    row = empty_result_row(fitclass)
    extra = metacal_columns() if metacal else []
    for c in extra:
        row[c.name] = (np.nan if c.dtype.startswith("f") else int(fitclass))
        if c.name.startswith("weight_"):
            row[c.name] = 0.0
    for c in output_columns() + extra:
        if c.name in CATALOG_COLUMNS:
            data = np.asarray(catalog[c.name]) if c.name == "id" else np.asarray(catalog[c.name], dtype=c.dtype)
        else:
            data = np.full(n, row[c.name], dtype=c.dtype)
        out[c.name] = Column(data, unit=c.unit or None, description=c.description)
    return out


_RESERVED = re.compile(r"^(SIMPLE|XTENSION|BITPIX|NAXIS\d*|PCOUNT|GCOUNT|TFIELDS|EXTEND|END|"
                       r"T(TYPE|FORM|UNIT|DIM|NULL|SCAL|ZERO|DISP)\d+)$")


def _cards(header_cards) -> list:
    """Normalise a header, mapping or iterable of cards to (key, value, comment) triples."""
    if header_cards is None:
        return []
    if isinstance(header_cards, fits.Header):
        return [(c.keyword, c.value, c.comment) for c in header_cards.cards]
    items = header_cards.items() if isinstance(header_cards, Mapping) else header_cards
    out = []
    for item in items:
        if isinstance(item, fits.Card):
            out.append((item.keyword, item.value, item.comment))
            continue
        key, value = item[0], item[1]
        comment = ""
        if isinstance(header_cards, Mapping) and isinstance(value, tuple):
            value, comment = value
        elif len(item) > 2:
            comment = item[2]
        out.append((key, value, comment))
    return out


def provenance_cards(config: Mapping[str, Any], version: Optional[str] = None,
                     extra: Optional[Mapping[str, Any]] = None) -> list:
    """Header cards recording a run: software version, the inner loops that ran, the full configuration.

    The configuration is one JSON string (FITS long-string CONTINUE cards),
    so ``json.loads(header['SFCONFIG'])`` gives it back exactly. ``SFKERNEL``
    is 'compiled' or 'numpy' (:func:`shearfit.engine.kernel.kernel_info`) and
    ``SFISA`` the instruction-set level the compiled loops ran at.

    Parameters
    ----------
    config : mapping
        E.g. :meth:`FieldConfig.to_dict`.
    version : str, optional
        Defaults to the installed shearfit version.
    extra : mapping, optional
        More ``key: value`` or ``key: (value, comment)`` cards (calibration, seed).
    """
    if version is None:
        from ..version import __version__ as version
    from ..engine.kernel import kernel_info

    kernel = kernel_info()
    cards = [("SFVERS", str(version), "shearfit version"),
             ("SFKERNEL", kernel["path"], "inner loops: compiled C or numpy"),
             ("SFISA", kernel["isa"], "instruction set of the compiled loops"),
             ("SFCONFIG", json.dumps(dict(config), default=str), "full configuration, JSON")]
    return cards + _cards(extra)


def write_catalog_atomic(table: Table, path, header_cards=None) -> None:
    """Write a table as a FITS binary table, atomically.

    The file is written under a temporary name in the target directory and
    renamed over ``path`` only once complete, so ``path`` never holds a
    half-written catalogue (a crash, a full disk or Ctrl-C leave the previous
    file, or nothing); the temporary file is removed on failure.

    Parameters
    ----------
    table : astropy.table.Table
    path : str or os.PathLike
    header_cards : astropy.io.fits.Header, mapping or iterable, optional
        Cards for the table HDU's header: ``(key, value[, comment])`` tuples,
        ``fits.Card`` objects or ``{key: value or (value, comment)}``. Keys
        longer than 8 characters become HIERARCH cards; long strings are
        continued.

    Raises
    ------
    ShearfitIOError
        The directory does not exist or is not writable, or writing fails.
    ShearfitValueError
        The table or a card cannot be represented in FITS.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise ShearfitIOError(f"{path}: cannot write: directory {directory} does not exist")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ShearfitIOError(f"{path}: cannot write: directory {directory} is not writable")
    if os.path.isdir(path):
        raise ShearfitIOError(f"{path}: cannot write: it is a directory")
    # Our own name rather than mkstemp: os.open with mode 0o666 lets the umask set the final
    # file's permissions, as for any other output; mkstemp would leave it private (0600).
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot write: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            try:
                hdu = fits.table_to_hdu(table)
                for key, value, comment in _cards(header_cards):
                    key = str(key)
                    if _RESERVED.match(key.upper()):
                        raise ShearfitValueError(f"header card {key} would change the table's structure")
                    if len(key) > 8 and not key.upper().startswith("HIERARCH "):
                        key = "HIERARCH " + key
                    hdu.header.append((key, value, comment), end=True)
                fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(fh)
            except ShearfitError:
                raise
            except OSError:
                raise
            except Exception as exc:
                raise ShearfitValueError(f"{path}: the table cannot be written as FITS ({_first_line(exc)})") \
                    from None
            fh.flush()
            # The rename must not become visible before the data are on disk.
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError) and not isinstance(exc, ShearfitError):
            raise ShearfitIOError(f"{path}: cannot write: {exc.strerror or _first_line(exc)}") from None
        raise
