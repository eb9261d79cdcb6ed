"""Calibrated shear two-point functions (sec. 8.5): ``shearfit xipm``.

xi+ and xi- of the lensfit-weighted ellipticities come from TreeCorr's
``GGCorrelation`` (the catalogue's e1, e2 are in TreeCorr's convention, see
INTERFACE.md). The multiplicative calibration enters as the paper's
ensemble correction: with m_i the calibration of galaxy i,

    1 + K(theta) = sum_ij w_i w_j (1 + m_i)(1 + m_j) / sum_ij w_i w_j

over the pairs of each bin (TreeCorr's ``KKCorrelation`` of k = 1 + m with
the same weights), and xi_cal = xi / (1 + K). The systematic covariance of
xi_cal comes from recomputing m_i, and so 1 + K, for (alpha, beta) pairs
drawn from the calibration's likelihood.
"""

from __future__ import annotations

import numpy as np
import treecorr
from astropy.table import Table

from ..calib.calibrate import load_calibration
from ..errors import ShearfitIOError, ShearfitValueError

__all__ = ["read_shear_catalog", "measured", "parse_selection", "xipm", "write_xipm", "metacal_response_of"]

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


def read_shear_catalog(path, selections=(), extra=None, measured_only=True) -> Table:
    """The measured galaxies of a shearfit catalogue (fitclass 0, weight > 0, finite e), after the selections.

    ``selections``: (column, lo, hi) ranges, e.g. a tomographic bin of a
    photometric-redshift column joined to the catalogue beforehand.
    ``measured_only=False`` keeps every object that passes the selections
    (a metacal selection response needs the objects that only the sheared
    versions select); :func:`measured` takes the galaxies from it.
    """
    try:
        t = Table.read(path)
    except (OSError, ValueError) as exc:
        raise ShearfitIOError(f"{path}: cannot read the shear catalogue: {str(exc).splitlines()[0]}") from None
    for col in tuple(_NEEDED) + tuple(extra or ()):
        if col not in t.colnames:
            raise ShearfitIOError(f"{path}: shear catalogue has no column {col!r}")
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


def _catalog(tab, k, with_shear=True):
    """TreeCorr catalogue of the galaxies' positions and weights, with k (and the ellipticities)."""
    cols = dict(ra=np.asarray(tab["ra"], float), dec=np.asarray(tab["dec"], float), ra_units="deg",
                dec_units="deg", w=np.asarray(tab["weight"], float), k=k)
    if with_shear:
        cols.update(g1=np.asarray(tab["e1"], float), g2=np.asarray(tab["e2"], float))
    return treecorr.Catalog(**cols)


def xipm(tab: Table, min_sep=1.0, max_sep=100.0, nbins=10, calibration=None, n_sys=100, seed=0, bin_slop=None,
         response=None):
    """xi+, xi- (raw and calibrated), 1 + K, errors and pair counts per bin; and the systematic covariance.

    The per-object m is the catalogue's ``m`` column unless a calibration
    file is given (then m(snr, scalelength) from its alpha, beta). With a
    calibration file holding the likelihood grid, ``n_sys`` draws of
    (alpha, beta) give the systematic covariance of (xip, xim) concatenated.
    ``response`` (a metacal catalogue's ensemble response R, 2x2) replaces
    1 + m by the mean of R's diagonal for every galaxy, so that 1 + K = R^2.
    Returns (table, covariance or None).
    """
    if len(tab) < 2:
        raise ShearfitValueError(f"{len(tab)} measured galaxies: two-point functions need at least 2")
    snr = np.asarray(tab["snr"], float) if "snr" in tab.colnames else None
    r = np.asarray(tab["scalelength"], float) if "scalelength" in tab.colnames else None
    if calibration is not None:
        if snr is None or r is None:
            raise ShearfitIOError("the catalogue needs snr and scalelength columns to apply a calibration file")
        model = load_calibration(calibration)
        m = model.m(snr, r)
    elif response is not None:
        m = np.full(len(tab), 0.5 * (response[0][0] + response[1][1]) - 1.0)
    elif "m" in tab.colnames:
        m = np.asarray(tab["m"], float)
    else:
        m = np.zeros(len(tab))
    m = np.where(np.isfinite(m), m, 0.0)
    cfg = dict(min_sep=min_sep, max_sep=max_sep, nbins=nbins, sep_units="arcmin", bin_slop=bin_slop)
    cat = _catalog(tab, 1.0 + m)
    gg = treecorr.GGCorrelation(**cfg)
    gg.process(cat)
    kk = treecorr.KKCorrelation(**cfg)
    kk.process(cat)
    # a bin without pairs (wider than the field) is NaN throughout, its theta the nominal one
    empty = gg.npairs == 0
    one_plus_k = np.where(empty, np.nan, kk.xi)
    out = Table({"theta": np.where(empty, gg.rnom, gg.meanr), "xip": gg.xip / one_plus_k, "xim": gg.xim / one_plus_k,
                 "xip_raw": gg.xip, "xim_raw": gg.xim, "xip_im": gg.xip_im, "one_plus_k": one_plus_k,
                 "sigma_xip": np.sqrt(gg.varxip) / one_plus_k, "sigma_xim": np.sqrt(gg.varxim) / one_plus_k,
                 "npairs": gg.npairs, "weight": gg.weight})
    cov = None
    if calibration is not None and n_sys > 0 and (model.kind == "binned" or model.grid is not None):
        rng = np.random.default_rng(seed)
        vecs = []
        for draw in model.draws(n_sys, rng):
            mk = draw.m(snr, r)
            k2 = treecorr.KKCorrelation(**cfg)
            k2.process(_catalog(tab, 1.0 + np.where(np.isfinite(mk), mk, 0.0), with_shear=False))
            k2xi = np.where(empty, np.nan, k2.xi)
            vecs.append(np.concatenate([gg.xip / k2xi, gg.xim / k2xi]))
        cov = np.cov(np.array(vecs), rowvar=False)
    return out, cov


def write_xipm(table: Table, cov, path, header_cards=()):
    """The xipm FITS file: HDU 1 the bins (INTERFACE.md), HDU SYSCOV the systematic covariance if any."""
    from astropy.io import fits

    from ..files import atomic_path

    hdus = [fits.PrimaryHDU(), fits.table_to_hdu(table)]
    hdus[1].name = "XIPM"
    for key, val, comment in header_cards:
        hdus[1].header[key] = (val, comment)
    if cov is not None:
        h = fits.ImageHDU(cov, name="SYSCOV")
        h.header["COMMENT"] = "systematic covariance of (xip, xim) from the calibration's (alpha, beta) likelihood"
        hdus.append(h)
    with atomic_path(path) as tmp:
        fits.HDUList(hdus).writeto(tmp)
