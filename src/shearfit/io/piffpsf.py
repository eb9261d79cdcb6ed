"""Piff PSF models given with a field (``psf: exp.piff``; docs/interface.rst, "Given PSF").

`Piff <https://github.com/rmjarvis/Piff>`_ (the Rubin/DES PSF code) writes its
fitted models as ``.piff`` files. :class:`PiffModel` reads one and gives, per
CCD, an object with the ``image_at(x, y)`` interface of
:class:`~shearfit.io.psfinput.PSFExModel`: the PSF at a 0-based CCD pixel
position, in the convention the engine's :class:`~shearfit.Observation`
takes (pixel response included, sum 1, centre at ``(ny // 2, nx // 2)``,
oversampling 1).

The ``piff`` package is an optional dependency: it is imported only when a
``.piff`` file is read, and its absence is a one-line error naming the file.

Conventions
-----------
Positions
    shearfit's (x, y) are 0-based numpy pixel positions (x along columns);
    Piff's, like GalSim's default image bounds and SExtractor's, are 1-based
    FITS image coordinates: Piff is asked for ``(X, Y) = (x + 1, y + 1)``.
Pixel frame
    The PSF is drawn on the CCD's own pixel grid, through the local Jacobian
    of the model's stored WCS for that chip at (X, Y) (the WCS Piff fitted
    the stars through, which is the image's own WCS).
Pixel response
    Piff models the stars as observed: what ``PSF.draw`` returns includes
    the pixel response (a pixel-basis model holds it already, an analytic
    one is convolved with the pixel when drawn); it is drawn here the same
    way (``PSF.draw`` with the model's own drawing method).
Centring
    The profile's nominal centre is placed on the centre of pixel
    ``(ny // 2, nx // 2)`` of the stamp (``center=`` of ``PSF.draw``); for an
    odd ``stamp_size`` that is ``PSF.draw(X, Y, chipnum, center=True)``.
Normalisation
    The stamp (``stamp_size`` pixels square, 25 by default) is divided by
    its sum, so flux beyond the stamp is left out.
Chip numbers
    A Piff model covers one or several chips, each under a ``chipnum`` (the
    keys of its stored WCS). CCD ``i`` of the exposure (0-based, in the image
    file's HDU order, as the given FITS PSF's HDUs) is, in this order of
    preference:

    1. the value of the CCD header's ``CHIPNUM``, else ``CCDNUM`` keyword
       (the DES convention), where every CCD has it and every value is one of
       the model's chipnums;
    2. the model's only chip, for a one-CCD exposure and a one-chip model;
    3. chipnum ``i`` (Piff's default: the index of the image in its input
       list), where ``0 .. n_ccd - 1`` are all chipnums of the model.

    Anything else is an error listing the model's chipnums; ``chipnums=``
    gives the mapping explicitly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ShearfitIOError, ShearfitValueError
from .psfinput import PSFImage

__all__ = ["PiffModel", "PiffCCD", "is_piff_path", "CHIPNUM_KEYWORDS"]

CHIPNUM_KEYWORDS = ("CHIPNUM", "CCDNUM")
"""CCD header keywords that name a CCD's Piff chipnum, in order of preference."""

_POSITION_PROPERTIES = {"x", "y", "u", "v"}


def is_piff_path(path) -> bool:
    """True if ``path`` names a Piff model by its suffix (``.piff``, any case)."""
    return str(path).lower().endswith(".piff")


def _one_line(exc):
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def _import_piff(path):
    try:
        import piff
    except ImportError as exc:
        raise ShearfitIOError(f"cannot read PSF file '{path}': install piff to read .piff PSF models "
                              f"(pip install piff; {_one_line(exc)})") from None
    return piff


def _header_chipnums(headers):
    """Chipnums from the CCD headers' CHIPNUM / CCDNUM, or None where not every header has an integer one."""
    if not headers or any(h is None for h in headers):
        return None
    for key in CHIPNUM_KEYWORDS:
        values = [h.get(key) for h in headers]
        try:
            if all(v is not None and float(v) == int(v) for v in values):
                return [int(v) for v in values]
        except (TypeError, ValueError):
            continue
    return None


class PiffModel:
    """A Piff PSF model file, read once; :meth:`for_ccd` gives the PSF of one CCD of the exposure.

    Parameters
    ----------
    path : str or Path
        The ``.piff`` file (written by ``piff.PSF.write`` or ``piffify``).
    n_ccd : int, optional
        CCDs in the exposure. With it the CCD -> chipnum mapping is resolved
        (and checked) at once; without it :meth:`for_ccd` resolves one CCD.
    chipnums : sequence of int, optional
        The chipnum of each CCD, explicitly (overrides the rules below).
    headers : sequence or dict of astropy.io.fits.Header, optional
        The CCDs' headers, for their ``CHIPNUM`` / ``CCDNUM`` keyword: a list
        (CCD ``i`` is item ``i``) or a dict {CCD index: header} (CCDs left out
        of the exposure may be missing from it).
    stamp_size : int
        Side of the PSF image :meth:`PiffCCD.image_at` returns, pixels.

    The mapping from CCD index to chipnum is described in the module doc.

    Raises
    ------
    ShearfitIOError
        The file is missing, is not a Piff model, or piff is not installed.
    ShearfitValueError
        The model needs interpolation properties shearfit cannot give (e.g. a
        colour), has no WCS, or its chips do not match the exposure's CCDs.
    """

    def __init__(self, path, n_ccd=None, chipnums=None, headers=None, stamp_size=25):
        self.path = Path(path)
        if not self.path.exists():
            raise ShearfitIOError(f"Piff PSF file '{self.path}' does not exist")
        if self.path.is_dir():
            raise ShearfitIOError(f"Piff PSF file '{self.path}' is a directory")
        stamp_size = int(stamp_size)
        if stamp_size < 5:
            raise ShearfitValueError(f"Piff PSF stamp_size must be at least 5 pixels, got {stamp_size}")
        self.stamp_size = stamp_size
        piff = _import_piff(self.path)
        try:
            psf = piff.read(str(self.path))
        except Exception as exc:   # noqa: BLE001 - piff/fitsio raise many types (AssertionError on a plain FITS file)
            raise ShearfitIOError(f"cannot read Piff PSF file '{self.path}': not a Piff model ({_one_line(exc)})") from None
        where = f"Piff PSF file '{self.path}'"
        if not isinstance(getattr(psf, "wcs", None), dict) or not psf.wcs:
            raise ShearfitValueError(f"{where}: the model holds no WCS (no chips); write it from a fit to images")
        extra = [p for p in getattr(psf, "interp_property_names", ()) if p not in _POSITION_PROPERTIES]
        if extra:
            raise ShearfitValueError(f"{where}: the model interpolates in {', '.join(map(str, extra))}, which shearfit "
                                     "cannot provide (only positions)")
        self.psf = psf
        self.model_chipnums = sorted(int(c) for c in psf.wcs)
        if headers is not None and not isinstance(headers, dict):
            headers = dict(enumerate(headers))
        self._headers = headers or None
        self.n_ccd = None if n_ccd is None else int(n_ccd)
        self.chipnums = None
        if chipnums is not None:
            chipnums = [int(c) for c in chipnums]
            bad = [c for c in chipnums if c not in self.model_chipnums]
            if bad:
                raise ShearfitValueError(f"{where}: chipnum(s) {bad} not in the model (it has {self.model_chipnums})")
            if self.n_ccd is not None and len(chipnums) != self.n_ccd:
                raise ShearfitValueError(f"{where}: {len(chipnums)} chipnums given for {self.n_ccd} CCDs")
            self.chipnums = chipnums
        elif self.n_ccd is not None:
            self.chipnums = self._resolve(self.n_ccd)

    def _resolve(self, n_ccd):
        """The chipnum of each of ``n_ccd`` CCDs (module doc: header keyword, only chip, index)."""
        have = set(self.model_chipnums)
        if self._headers is not None:
            known = sorted(i for i in self._headers if 0 <= i < n_ccd)
            from_headers = _header_chipnums([self._headers[i] for i in known])
            if from_headers is not None and set(from_headers) <= have:
                chips = [None] * n_ccd        # CCDs without a header (left out of the exposure) get none
                for i, c in zip(known, from_headers):
                    chips[i] = c
                return chips
        if n_ccd == 1 and len(have) == 1:
            return [self.model_chipnums[0]]
        if set(range(n_ccd)) <= have:
            return list(range(n_ccd))
        raise ShearfitValueError(
            f"Piff PSF file '{self.path}': cannot match the exposure's {n_ccd} CCD(s) to the model's chipnums "
            f"{self.model_chipnums} (by a {'/'.join(CHIPNUM_KEYWORDS)} header keyword, the only chip, or the "
            f"CCD index 0..{n_ccd - 1})")

    def chipnum(self, i):
        """Piff chipnum of CCD ``i`` of the exposure."""
        i = int(i)
        if self.chipnums is not None:
            if not 0 <= i < len(self.chipnums):
                raise ShearfitValueError(f"Piff PSF file '{self.path}': no CCD {i} (the exposure has "
                                         f"{len(self.chipnums)})")
            if self.chipnums[i] is None:
                raise ShearfitValueError(f"Piff PSF file '{self.path}': CCD {i} has no {'/'.join(CHIPNUM_KEYWORDS)} "
                                         "header keyword to match a chip")
            return self.chipnums[i]
        if i < 0:
            raise ShearfitValueError(f"Piff PSF file '{self.path}': no CCD {i}")
        if len(self.model_chipnums) == 1 and i == 0:
            return self.model_chipnums[0]
        if i in self.model_chipnums:
            return i
        raise ShearfitValueError(f"Piff PSF file '{self.path}': no chipnum {i} in the model "
                                 f"(it has {self.model_chipnums})")

    def for_ccd(self, i):
        """The PSF of CCD ``i`` (0-based): a :class:`PiffCCD` with ``image_at(x, y)``."""
        return PiffCCD(self, self.chipnum(i))

    def __repr__(self):
        return (f"PiffModel('{self.path}', {type(self.psf).__name__}, chipnums={self.model_chipnums}, "
                f"stamp_size={self.stamp_size})")


class PiffCCD:
    """The Piff model of one chip, with the ``image_at(x, y)`` interface of :class:`PSFExModel`."""

    oversampling = 1

    def __init__(self, model: PiffModel, chipnum: int):
        self.model = model
        self.chipnum = chipnum
        self._chip = next(c for c in model.psf.wcs if int(c) == chipnum)   # the key as Piff stored it

    @property
    def shape(self):
        """Shape (ny, nx) of the arrays :meth:`image_at` returns."""
        return (self.model.stamp_size, self.model.stamp_size)

    def draw(self, x, y):
        """Piff's drawing at 0-based pixel (x, y), centred on pixel ``(ny // 2, nx // 2)``, not normalised.

        Returns the ``galsim.Image`` ``PSF.draw`` fills (flux 1 over the whole
        plane, so it sums to a little less than 1 on the stamp).
        """
        import galsim

        n = self.model.stamp_size
        X, Y = float(x) + 1.0, float(y) + 1.0        # Piff/GalSim/FITS image positions are 1-based
        wcs = self.model.psf.wcs[self._chip]
        # the stamp's bounds around the position as Piff lays them out; its WCS the local Jacobian at (X, Y)
        x0 = int(np.ceil(X - (0.5 if n % 2 == 1 else 0))) - n // 2
        y0 = int(np.ceil(Y - (0.5 if n % 2 == 1 else 0))) - n // 2
        b = galsim.BoundsI(x0, x0 + n - 1, y0, y0 + n - 1)
        image = galsim.ImageD(b, wcs=wcs.local(image_pos=galsim.PositionD(X, Y)))
        centre = (float(b.xmin + n // 2), float(b.ymin + n // 2))      # array index (n // 2, n // 2)
        try:
            return self.model.psf.draw(X, Y, chipnum=self._chip, flux=1.0, center=centre, image=image)
        except Exception as exc:   # noqa: BLE001 - Piff's interpolators raise various types
            raise ShearfitValueError(f"Piff PSF file '{self.model.path}': cannot draw chip {self.chipnum} at "
                                     f"(x, y) = ({x}, {y}) ({_one_line(exc)})") from None

    def image_at(self, x, y):
        """The PSF at 0-based CCD pixel (x, y): ``(image, 1)``, image float64 summing to 1, centre ``(n // 2, n // 2)``."""
        img = np.array(self.draw(x, y).array, dtype=np.float64)
        total = float(img.sum())
        if not (np.isfinite(total) and total > 0):
            raise ShearfitValueError(f"Piff PSF file '{self.model.path}' chip {self.chipnum} at (x, y) = ({x}, {y}): "
                                     f"the PSF sums to {total:.6g}, cannot normalise")
        img /= total
        img.setflags(write=False)
        return PSFImage(img, 1)

    def __repr__(self):
        return f"PiffCCD('{self.model.path}', chipnum={self.chipnum}, stamp_size={self.model.stamp_size})"
