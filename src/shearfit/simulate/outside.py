"""Galaxies outside lensfit's model family, drawn by GalSim, for measuring model bias.

lensfit fits a truncated exponential disk plus a de Vaucouleurs bulge sharing
one ellipticity (sec. 3.1). Real galaxies are none of these exactly. This
module draws three families unlike the model, each with a half-light radius
log-uniform in ``hlr_range`` (0.1-2 arcsec by default) and the paper's prior
ellipticity (:func:`shearfit.engine.priors.sample_population`):

``sersic``
    one Sersic profile of index n uniform in [0.3, 6] (GalSim's range),
    truncated at ``SERSIC_TRUNCATION`` half-light radii;
``bulge_disk``
    an exponential disk and a de Vaucouleurs bulge (B/T uniform in
    [0.1, 0.7], bulge half-light radius 0.2-0.8 of the disk's) whose
    ellipticities are drawn independently, so that their axis ratios and
    position angles differ;
``knots``
    an exponential disk with star-forming knots (``galsim.RandomKnots``, 10-100
    points spread like the disk, 10-50 % of the light), the knots' positions
    fixed per galaxy (a GalSim seed drawn from the generator).

``outside_population(mags, rng, cfg)`` is a population for
:func:`shearfit.simulate.stamps.ring_set` and ``outside_profile`` its profile
hook: ring members are the same galaxy turned by ``pi j / n`` as a whole (every
component and knot with it), which cancels the intrinsic shapes of any profile
in the ring's mean, then sheared.
"""

from __future__ import annotations

import galsim
import numpy as np

from .stamps import intrinsic_shape

__all__ = ["FAMILIES", "SERSIC_TRUNCATION", "outside_population", "outside_profile"]

#: the families, in the order of their integer code (the ``family`` field)
FAMILIES = ("sersic", "bulge_disk", "knots")
#: Sersic profiles are truncated at this many half-light radii (an n = 6 profile has 1 % of its light beyond 40)
SERSIC_TRUNCATION = 5.0
#: extent of a drawn galaxy in half-light radii, for the stamp check of ring_set (its ``scalelength`` field is
#: this extent / 4.5, the paper's truncation in scalelengths)
_EXTENT_HLR = 5.0


def _prior_e(mags, rng, cfg):
    from ..engine.priors import sample_population

    rec = sample_population(np.asarray(mags, float), rng, cfg)
    return np.asarray(rec["e1"], float), np.asarray(rec["e2"], float)


def outside_population(mags, rng, cfg=None, hlr_range=(0.1, 2.0), families=FAMILIES):
    """Parameters of galaxies outside the model family, one per magnitude (a dict of arrays).

    Fields: ``family`` (index in :data:`FAMILIES`), ``hlr`` (arcsec), ``e1``, ``e2`` (the galaxy's, or the
    disk's), ``sersic_n``, ``bulge_fraction``, ``bulge_hlr_ratio``, ``bulge_e1``, ``bulge_e2``,
    ``knot_fraction``, ``n_knots``, ``knot_seed``, and ``scalelength`` (the extent / 4.5, for ring_set's
    stamp check), ``is_bulge`` (False).
    """
    mags = np.atleast_1d(np.asarray(mags, float))
    n = mags.size
    codes = np.array([FAMILIES.index(f) for f in families])
    family = codes[rng.integers(0, codes.size, n)]
    hlr = np.exp(rng.uniform(np.log(hlr_range[0]), np.log(hlr_range[1]), n))
    e1, e2 = _prior_e(mags, rng, cfg)
    be1, be2 = _prior_e(mags, rng, cfg)
    return {
        "family": family, "hlr": hlr, "e1": e1, "e2": e2,
        "sersic_n": rng.uniform(0.3, 6.0, n),
        "bulge_fraction": rng.uniform(0.1, 0.7, n), "bulge_hlr_ratio": rng.uniform(0.2, 0.8, n),
        "bulge_e1": be1, "bulge_e2": be2,
        "knot_fraction": rng.uniform(0.1, 0.5, n), "n_knots": rng.integers(10, 101, n),
        "knot_seed": rng.integers(1, 2 ** 31 - 1, n),
        "scalelength": _EXTENT_HLR * hlr / 4.5, "is_bulge": np.zeros(n, bool),
    }


def outside_profile(pop, angle, g1, g2, flux, gsparams=None):
    """The GalSim profile of one galaxy of :func:`outside_population` (``pop``: its fields as scalars), turned
    by ``angle`` radians as a whole, then sheared by (g1, g2), of total flux ``flux``."""
    fam = FAMILIES[int(pop["family"])]
    hlr = float(pop["hlr"])
    e1, e2 = float(pop["e1"]), float(pop["e2"])
    if fam == "sersic":
        prof = galsim.Sersic(n=float(pop["sersic_n"]), half_light_radius=hlr, trunc=SERSIC_TRUNCATION * hlr,
                             flux_untruncated=False, gsparams=gsparams)
        prof = intrinsic_shape(prof, e1, e2)
    elif fam == "bulge_disk":
        B = float(pop["bulge_fraction"])
        disk = intrinsic_shape(galsim.Exponential(half_light_radius=hlr, gsparams=gsparams), e1, e2).withFlux(1.0 - B)
        rb = float(pop["bulge_hlr_ratio"]) * hlr
        bulge = galsim.DeVaucouleurs(half_light_radius=rb, trunc=SERSIC_TRUNCATION * rb, gsparams=gsparams)
        bulge = intrinsic_shape(bulge, float(pop["bulge_e1"]), float(pop["bulge_e2"])).withFlux(B)
        prof = galsim.Add([disk, bulge], gsparams=gsparams)
    elif fam == "knots":
        fk = float(pop["knot_fraction"])
        disk = galsim.Exponential(half_light_radius=hlr, gsparams=gsparams).withFlux(1.0 - fk)
        knots = galsim.RandomKnots(int(pop["n_knots"]), half_light_radius=hlr, flux=fk,
                                   rng=galsim.BaseDeviate(int(pop["knot_seed"])), gsparams=gsparams)
        prof = intrinsic_shape(galsim.Add([disk, knots], gsparams=gsparams), e1, e2)
    else:   # pragma: no cover - FAMILIES is closed
        raise ValueError(fam)
    if angle:
        prof = prof.rotate(float(angle) * galsim.radians)
    if g1 or g2:
        prof = prof.shear(g1=float(g1), g2=float(g2))
    return prof.withFlux(float(flux))
