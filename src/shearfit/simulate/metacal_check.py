"""Metacal's response against GalSim's true shear response, at fixed samples.

A galaxy rendered by GalSim unsheared and at true shears of +-h in each component (the same galaxy,
PSFs, dithers and noise: :func:`shear_sets`) goes through metacal's operations; one joint fit chooses
the samples (the noshear version of the unsheared stamps) and every other image replays them
(:func:`shearfit.engine.measure.measure_versions`). Then metacal's ``R_ii = (e_i[i+] - e_i[i-]) / 2 delta`` and
the true-shear response ``A_ii = (e_i[+h] - e_i[-h]) / 2 h`` of the noshear fit are both smooth in the
pixels, and agree per galaxy as closely as metacal's images reproduce a true shear
(:func:`fixed_sample_responses`). Used by ``benchmarks/metacal_noise_free.py`` and the tests.
"""

from __future__ import annotations

import numpy as np

from ..calib import metacal
from ..engine.measure import measure_object, measure_versions
from ..observation import Observation
from .stamps import NegatedNormal, ring_set

#: Scale of the symmetrising noise in noise-free comparisons (the weights are scaled back by its square).
QUIET = 1e-9


class QuietNormal:
    """A generator whose normal deviates are scaled by :data:`QUIET`: metacal's symmetrising noise out of
    the way."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)

    def normal(self, loc, scale, size):
        return QUIET * self.rng.normal(loc, scale, size)


def rescaled(versions):
    """Versions made with :class:`QuietNormal` noise, their weights scaled back to the stamps' noise level."""
    return {k: Observation(image=v.image, weight=v.weight * QUIET ** 2, psf=v.psf,
                           psf_oversampling=v.psf_oversampling, jacobian=v.jacobian, offset=v.offset,
                           flux_scale=v.flux_scale, psf_moffat=v.psf_moffat) for k, v in versions.items()}


def shear_sets(n_galaxies, h, seed, **ring_kwargs):
    """Ring sets (one orientation) of the same galaxies unsheared and at shears +-h in each component:
    ``{(g1, g2): ring_set(...)}``."""
    shears = [(0.0, 0.0), (h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)]
    return {s: ring_set(n_galaxies, s, np.random.default_rng(seed), n_rotations=1, **ring_kwargs) for s in shears}


def fixed_sample_responses(sets, i, h, delta, config, seed, noisy=False, twin=False, free=True, psf="dilated",
                           own=False, own_position=False, own_samples=False):
    """Galaxy ``i`` of :func:`shear_sets`: its diagonal responses ``(R, A, A_free, fitclasses)``.

    R: metacal's; A: the noshear fit's to the true shear, both replaying the choices of the unsheared
    noshear fit; A_free (None unless ``free``): the same true-shear difference with each noshear image
    fitted on its own (its own modes, position, sizes and samples: the estimator as it runs on data).
    ``noisy``: the stamps carry their noise and metacal its symmetrising noise (minus both for the
    antithetic ``twin``); otherwise the symmetrising noise is :class:`QuietNormal`. ``psf``: metacal's new PSF
    (:func:`shearfit.calib.metacal.metacal_observations`). ``own``: every image fitted on its own instead (R as
    ``measure_metacal(..., replay=False)`` measures it, A the same as A_free; A_free is then None).
    ``own_position``: the replays find their own position (``measure_metacal(..., own_position=True)``);
    ``own_samples``: their own ellipticity grid (``measure_metacal(..., own_samples=True)``).
    """
    def rng(j):
        # exposure j's symmetrising noise: its own field, the same for the galaxy at 0 and +-h
        if not noisy:
            return QuietNormal([seed, j])
        r = np.random.default_rng([seed, i, j])
        return NegatedNormal(r) if twin else r

    def prepared(obs, j, versions=tuple(metacal.VERSIONS)):
        v = metacal.metacal_observations(obs, delta, rng(j), versions=versions, psf=psf)
        return v if noisy else rescaled(v)

    per = [prepared(ob, j) for j, ob in enumerate(sets[(0.0, 0.0)][i][0])]
    versions = [[d[name] for d in per] for name in metacal.VERSIONS]
    for s in [(h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)]:
        versions.append([prepared(ob, j, ("noshear",))["noshear"] for j, ob in enumerate(sets[s][i][0])])
    mag = sets[(0.0, 0.0)][i][1]["mag"]
    if own:
        r = [measure_object(v, mag, config) for v in versions]
        R = np.array([(r[1].e1 - r[2].e1), (r[3].e2 - r[4].e2)]) / (2 * delta)
        A = np.array([(r[5].e1 - r[6].e1), (r[7].e2 - r[8].e2)]) / (2 * h)
        return R, A, None, [x.fitclass for x in r]
    r = measure_versions(versions, mag, config, margin=10.0, own_position=own_position, own_samples=own_samples)
    R = np.array([(r[1].e1 - r[2].e1), (r[3].e2 - r[4].e2)]) / (2 * delta)
    A = np.array([(r[5].e1 - r[6].e1), (r[7].e2 - r[8].e2)]) / (2 * h)
    if not free:
        return R, A, None, [x.fitclass for x in r]
    own = [measure_object(v, mag, config) for v in versions[5:]]
    A_free = np.array([(own[0].e1 - own[1].e1), (own[2].e2 - own[3].e2)]) / (2 * h)
    return R, A, A_free, [x.fitclass for x in r + own]
