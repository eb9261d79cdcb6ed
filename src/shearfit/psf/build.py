"""PSF models of whole exposures: star selection (sec. 5), the fit, model files.

:func:`select_stars` applies the paper's cuts to the stars of one exposure
(integrated SNR > 20, central pixel below half of SATURATE, no unusable
pixel in the stamp, no other catalogue object within 8 pixels) and weights
them by nu^2 / (nu^2 + 50^2); CCDs with fewer than ``psf_min_stars``
usable stars are left out of the model, and the objects on them are not
measured on that exposure. Without a star catalogue, stars are picked from
the object catalogue on the size-magnitude locus (:func:`stellar_locus`).
:func:`build_exposure_psf` fits the model and :func:`write_psf_model` /
:func:`read_psf_model` store it.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits
from scipy.spatial import cKDTree

from ..files import atomic_path
from ..errors import ShearfitIOError, ShearfitValueError
from ..io.stamps import cut_stamp, locate_all
from ..io.wcs import pixel_to_sky, tangent_plane_offsets
from .pixelmodel import PixelPSF, StarSet, fit_pixel_psf

log = logging.getLogger(__name__)

__all__ = ["FieldFrame", "TooFewStarsError", "select_stars", "stellar_locus", "build_exposure_psf", "write_psf_model",
           "read_psf_model", "is_psf_model_file", "ExposurePSFResult"]

APERTURE_RADIUS = 8.0   # pixels: the integrated SNR's aperture


class TooFewStarsError(ShearfitValueError):
    """No CCD of an exposure has ``psf_min_stars`` usable stars: no PSF model can be fitted to it.

    ``shearfit psf`` stops on it; ``shearfit measure`` leaves the exposure out with a warning.
    """


@dataclass
class FieldFrame:
    """Field coordinates of an exposure: tangent-plane offsets from its centre, scaled to about [-1, 1]."""

    ra0: float
    dec0: float
    scale: float   # arcsec per unit of u, v

    @classmethod
    def of_exposure(cls, ccds) -> "FieldFrame":
        corners = []
        for c in ccds:
            ny, nx = c.shape
            xs = np.array([0, nx - 1, 0, nx - 1, (nx - 1) / 2])
            ys = np.array([0, 0, ny - 1, ny - 1, (ny - 1) / 2])
            ra, dec = pixel_to_sky(c.wcs, xs, ys)
            corners.append(np.stack([ra, dec], axis=1))
        pts = np.concatenate(corners)
        # the centre: mean unit vector of the corners
        r, d = np.radians(pts[:, 0]), np.radians(pts[:, 1])
        vec = np.stack([np.cos(d) * np.cos(r), np.cos(d) * np.sin(r), np.sin(d)], axis=1).mean(axis=0)
        ra0 = float(np.degrees(np.arctan2(vec[1], vec[0])) % 360.0)
        dec0 = float(np.degrees(np.arctan2(vec[2], np.hypot(vec[0], vec[1]))))
        u, v = tangent_plane_offsets(pts[:, 0], pts[:, 1], ra0, dec0)
        scale = float(max(np.max(np.abs(u)), np.max(np.abs(v)), 1.0))
        return cls(ra0, dec0, scale)

    def uv(self, ra, dec):
        u, v = tangent_plane_offsets(ra, dec, self.ra0, self.dec0)
        return np.asarray(u) / self.scale, np.asarray(v) / self.scale

    def to_dict(self):
        return {"ra0": self.ra0, "dec0": self.dec0, "scale": self.scale}


@dataclass
class ExposurePSFResult:
    model: PixelPSF
    stars: StarSet
    info: dict
    n_candidates: np.ndarray          # per CCD, stars on it before the cuts
    n_usable: np.ndarray              # per CCD, after the cuts
    rejected: dict = field(default_factory=dict)   # reason -> count
    notes: list = field(default_factory=list)


@functools.lru_cache(maxsize=8)
def _aperture(n):
    """The flat indices of the pixels of an n x n stamp within APERTURE_RADIUS of its centre pixel (read-only,
    shared)."""
    c = np.arange(n) - n // 2
    ap = np.flatnonzero((c[:, None] ** 2 + c[None, :] ** 2) <= APERTURE_RADIUS ** 2)
    ap.setflags(write=False)
    return ap


def _integrated_snr(img, w):
    ap = _aperture(img.shape[-1])
    flux = float(np.sum(img.ravel()[ap]))
    var = float(np.sum(1.0 / w.ravel()[ap]))
    return flux / np.sqrt(var) if var > 0 else 0.0


def select_stars(ccds, ra, dec, others_ra, others_dec, pc, frame: FieldFrame):
    """Cut and select the stars of one exposure (see module doc).

    Returns (StarSet of usable stars, the index into ``ra``/``dec`` of each, candidates per CCD,
    usable per CCD, rejection counts).
    """
    n = int(pc.psf_size)
    hits = locate_all(ccds, ra, dec)
    rejected = {"off CCD edge or unusable pixel": 0, "SNR below minimum": 0, "saturated": 0, "neighbour": 0}
    cand = np.zeros(len(ccds), int)
    rows = {k: [] for k in ("image", "ivar", "delta", "ccd", "x", "y", "snr")}
    index = []
    # per candidate, whether another object lies within psf_isolation_radius: those within it less those within
    # 0.5 pixel (the star itself is in the catalogue of objects too, at distance ~0), one query per CCD
    crowded = np.zeros(hits.object.size, bool)
    for c in np.unique(hits.ccd):
        on = np.flatnonzero(hits.ccd == c)
        h2 = locate_all([ccds[c]], others_ra, others_dec)
        if h2.x.size:
            tree = cKDTree(np.stack([h2.x, h2.y], axis=1))
            pts = np.stack([hits.x[on], hits.y[on]], axis=1)
            crowded[on] = (tree.query_ball_point(pts, pc.psf_isolation_radius, return_length=True)
                           > tree.query_ball_point(pts, 0.5, return_length=True))
    for obj, c, x, y, near in zip(hits.object, hits.ccd, hits.x, hits.y, crowded):
        cand[c] += 1
        ccd = ccds[c]
        st = cut_stamp(ccd.image, ccd.pixel_weight, x, y, n)
        if st is None or np.any(st.weight <= 0):
            rejected["off CCD edge or unusable pixel"] += 1
            continue
        if near:
            rejected["neighbour"] += 1
            continue
        peak = float(st.image[n // 2, n // 2])
        if np.isfinite(ccd.saturate) and peak > pc.psf_saturation_fraction * ccd.saturate:
            rejected["saturated"] += 1
            continue
        snr = _integrated_snr(st.image, st.weight)
        if not snr > pc.psf_min_snr:
            rejected["SNR below minimum"] += 1
            continue
        rows["image"].append(st.image)
        rows["ivar"].append(st.weight)
        rows["delta"].append(st.offset)
        rows["ccd"].append(c)
        rows["x"].append(x)
        rows["y"].append(y)
        rows["snr"].append(snr)
        index.append(obj)
    if not rows["image"]:
        stars = StarSet(np.zeros((0, n, n)), np.zeros((0, n, n)), np.zeros((0, 2)), np.zeros(0, int),
                        *(np.zeros(0) for _ in range(5)))
    else:
        # the stars' field coordinates, in one call
        u, v = frame.uv(ra[np.array(index, int)], dec[np.array(index, int)])
        stars = StarSet(image=np.array(rows["image"]), ivar=np.array(rows["ivar"]),
                        delta=np.array(rows["delta"], float), ccd=np.array(rows["ccd"], int),
                        u=np.array(u, float), v=np.array(v, float), x=np.array(rows["x"]),
                        y=np.array(rows["y"]), snr=np.array(rows["snr"]))
    usable = np.bincount(stars.ccd, minlength=len(ccds)) if len(stars) else np.zeros(len(ccds), int)
    return stars, np.array(index, int), cand, usable, rejected


def stellar_locus(ccds, catalog, pc, frame, max_candidates=2000):
    """Stars picked from the object catalogue on the size-magnitude locus (no star catalogue given).

    Every bright, isolated, unsaturated object's adaptive-moment size is
    measured on the first CCD that holds it; the stellar locus is the
    narrow band of the smallest sizes (the median of the smallest quarter
    of objects with SNR above 50), and objects within 10 % of it are taken.
    """
    import galsim

    ra = np.asarray(catalog["ra"], float)
    dec = np.asarray(catalog["dec"], float)
    order = np.argsort(np.asarray(catalog["mag"], float))[:max_candidates]
    stars, index, _, _, _ = select_stars(ccds, ra[order], dec[order], ra, dec, pc, frame)
    if len(stars) == 0:
        return np.zeros(0, int)
    sig = np.full(len(stars), np.nan)
    for i in range(len(stars)):
        try:
            sig[i] = galsim.hsm.FindAdaptiveMom(galsim.Image(stars.image[i])).moments_sigma
        except galsim.errors.GalSimHSMError:
            pass
    ok = np.isfinite(sig) & (stars.snr > 50)
    if np.sum(ok) < 5:
        return np.zeros(0, int)
    s = np.sort(sig[ok])
    locus = float(np.median(s[: max(len(s) // 4, 3)]))
    keep = np.isfinite(sig) & (np.abs(sig / locus - 1) < 0.1)
    rows = order[index]
    return np.unique(rows[keep])


def build_exposure_psf(ccds, star_ra, star_dec, others_ra, others_dec, pc, label="exposure") -> ExposurePSFResult:
    """Select the stars of one exposure and fit its pixel PSF model."""
    frame = FieldFrame.of_exposure(ccds)
    stars, _, cand, usable, rejected = select_stars(ccds, star_ra, star_dec, others_ra, others_dec, pc, frame)
    notes = []
    good_ccd = usable >= pc.psf_min_stars
    for c in np.nonzero(~good_ccd)[0]:
        notes.append(f"{label}: CCD {c} ({ccds[c].label}) has {usable[c]} usable stars, fewer than "
                     f"psf_min_stars={pc.psf_min_stars}; it is left out")
    keep = good_ccd[stars.ccd] if len(stars) else np.zeros(0, bool)
    stars = stars.subset(keep)
    if len(stars) == 0:
        raise TooFewStarsError(f"{label}: no CCD has psf_min_stars={pc.psf_min_stars} usable stars "
                                 f"({int(cand.sum())} stars on the exposure, {int(usable.sum())} pass the cuts)")
    model, used, info = fit_pixel_psf(
        stars, len(ccds), order=pc.psf_order, oversampling=pc.psf_oversampling, ccd_terms=True,
        alias_order=pc.psf_alias_order, iterations=pc.psf_iterations, clip=pc.psf_clip,
        registration_order=pc.registration_order, ccd_shape=[c.shape for c in ccds], frame=frame.to_dict(),
        native_width=pc.psf_native_width)
    return ExposurePSFResult(model=model, stars=used, info=info, n_candidates=cand, n_usable=usable,
                             rejected=rejected, notes=notes)


# --- files -----------------------------------------------------------------------------------

MODEL_KEY = "SFPSFMOD"


def is_psf_model_file(path) -> bool:
    try:
        with fits.open(path) as h:
            return bool(h[0].header.get(MODEL_KEY, False))
    except (OSError, ValueError):
        return False


def write_psf_model(model: PixelPSF, path, extra_cards=()):
    """Write a fitted model (atomically: a temporary name, then rename)."""
    ph = fits.Header()
    ph[MODEL_KEY] = (True, "shearfit pixel PSF model")
    ph["PSFSIZE"] = (model.size, "native stamp side, pixels")
    ph["OVERSAMP"] = (model.oversampling, "model samples per pixel")
    ph["PSFORDER"] = (model.order, "polynomial order over the field")
    ph["NCCD"] = (model.n_ccd, "CCDs of the exposure")
    ph["REGORDER"] = (model.registration_order, "registration polynomial order per CCD")
    ph["ALIASORD"] = (model.alias_order, "order of the above-Nyquist terms")
    ph["RA0"] = (model.frame.get("ra0", 0.0), "field centre RA, deg")
    ph["DEC0"] = (model.frame.get("dec0", 0.0), "field centre Dec, deg")
    ph["FSCALE"] = (model.frame.get("scale", 1.0), "arcsec per unit field coordinate")
    for k, v, c in extra_cards:
        ph[k] = (v, c)
    terms = fits.BinTableHDU.from_columns([
        fits.Column("kind", "J", array=model.kind), fits.Column("ccd", "J", array=model.term_ccd),
        fits.Column("pu", "J", array=model.powers[:, 0]), fits.Column("pv", "J", array=model.powers[:, 1])],
        name="TERMS")
    reg = model.registration if model.registration is not None else np.zeros((model.n_ccd, 2, 1))
    shape = model.ccd_shape if model.ccd_shape is not None else np.zeros((model.n_ccd, 2))
    ccd = fits.BinTableHDU.from_columns([
        fits.Column("used", "L", array=model.ccd_used), fits.Column("ny", "J", array=np.asarray(shape)[:, 0]),
        fits.Column("nx", "J", array=np.asarray(shape)[:, 1]),
        fits.Column("reg", f"{reg.shape[1] * reg.shape[2]}D", array=reg.reshape(model.n_ccd, -1))], name="CCDS")
    hdul = fits.HDUList([fits.PrimaryHDU(header=ph), terms, ccd,
                         fits.ImageHDU(model.spectra.real, name="SPEC_RE"),
                         fits.ImageHDU(model.spectra.imag, name="SPEC_IM")])
    with atomic_path(path) as tmp:
        hdul.writeto(tmp, overwrite=True)


def read_psf_model(path) -> PixelPSF:
    try:
        with fits.open(path) as h:
            ph = h[0].header
            if not ph.get(MODEL_KEY, False):
                raise ShearfitIOError(f"{path}: not a shearfit PSF model (no {MODEL_KEY} in the primary header)")
            for name in ("TERMS", "CCDS", "SPEC_RE", "SPEC_IM"):
                if name not in h:
                    raise ShearfitIOError(f"{path}: PSF model has no HDU {name}")
            t, c = h["TERMS"].data, h["CCDS"].data
            n_ccd = int(ph["NCCD"])
            reg = np.asarray(c["reg"], float).reshape(n_ccd, 2, -1)
            return PixelPSF(size=int(ph["PSFSIZE"]), oversampling=int(ph["OVERSAMP"]), order=int(ph["PSFORDER"]),
                            n_ccd=n_ccd, kind=np.asarray(t["kind"], int), term_ccd=np.asarray(t["ccd"], int),
                            powers=np.stack([t["pu"], t["pv"]], axis=1).astype(int),
                            spectra=h["SPEC_RE"].data.astype(float) + 1j * h["SPEC_IM"].data.astype(float),
                            ccd_used=np.asarray(c["used"], bool),
                            frame={"ra0": float(ph["RA0"]), "dec0": float(ph["DEC0"]), "scale": float(ph["FSCALE"])},
                            registration=reg, registration_order=int(ph["REGORDER"]),
                            alias_order=int(ph.get("ALIASORD", 0)),
                            ccd_shape=np.stack([c["ny"], c["nx"]], axis=1))
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot read the PSF model: {exc}") from None
    except KeyError as exc:
        raise ShearfitIOError(f"{path}: PSF model header lacks {exc}") from None
