"""Shear bias of the whole engine on GalSim ring tests (tier 3, statistical).

Galaxies of the paper's population are rendered by GalSim (never by
shearfit) at 4 orientations with shear +g and -g. The images are noise-free
but carry the weights of SNR 100-200, so each likelihood has the width of that
SNR and is centred on the truth: what remains is the implementation's bias
and the likelihood-mean estimator's own bias for broad, asymmetric surfaces
(App. C; about +1 % in m, from the smallest galaxies, measured with
benchmarks/ring_test.py --noise-free). Tolerances are the bootstrap error
(whole rings resampled) times 3, plus that known estimator allowance.

The default run is a reduced form (a few rings, 3 exposures); ``-m slow``
runs the full one.
"""

import numpy as np
import pytest

import shearfit
from shearfit.calib.bias import ring_sums, shear_bias
from shearfit.simulate.stamps import ring_set

G = np.array([0.03, -0.02])


def _run(n_gal, n_exp, seed):
    rows = {k: [] for k in ("galaxy", "sign", "e1", "e2", "weight", "fitclass")}
    for i in range(n_gal):
        cache = {}
        for sign in (1, -1):
            rings = ring_set(1, tuple(sign * G), np.random.default_rng([seed, i]), n_rotations=4,
                             n_exposures=n_exp, snr_range=(100, 200), add_noise=False, draw_cache=cache)
            for obs, truth in rings:
                res = shearfit.measure_object(obs, mag=truth["mag"])
                for k, v in (("galaxy", i), ("sign", sign), ("e1", res.e1), ("e2", res.e2),
                             ("weight", res.weight), ("fitclass", res.fitclass)):
                    rows[k].append(v)
    tab = {k: np.array(v) for k, v in rows.items()}
    est, err = shear_bias(ring_sums(tab, n_gal), G, 500, np.random.default_rng(0))
    return est, err


def _check(est, err, estimator_allowance):
    m, c = est[:2], est[2:]
    em, ec = err[:2], err[2:]
    assert np.all(np.isfinite(est)) and np.all(np.isfinite(err))
    assert np.all(np.abs(m) < 3 * em + estimator_allowance), (m, em)
    assert np.all(np.abs(c) < 3 * ec + 2e-4), (c, ec)


def test_ring_reduced():
    est, err = _run(n_gal=4, n_exp=3, seed=5)
    # a sign error or a factor-2 error in the response would be m = -2 or -1/2: far outside
    _check(est, err, estimator_allowance=0.03)


@pytest.mark.slow
def test_ring_full():
    est, err = _run(n_gal=60, n_exp=7, seed=6)
    _check(est, err, estimator_allowance=0.015)


def _synthetic_rings(n_gal=40, m0=0.01, k=3.0, seed=3):
    """Rings whose estimates respond to shear with exactly 1 + m0 (plus a noise shared by each +g / -g pair) and
    whose weights exp(k e_par) grow with the estimate's component along the galaxy's own ellipticity."""
    rng = np.random.default_rng(seed)
    rows = {c: [] for c in ("galaxy", "rotation", "sign", "e1", "e2", "weight", "fitclass")}
    for i in range(n_gal):
        e0 = rng.uniform(0.1, 0.6) * np.exp(2j * rng.uniform(0, np.pi))
        for j in range(4):
            e = e0 * np.exp(1j * np.pi * j / 2)
            noise = complex(*rng.normal(0, 0.05, 2))
            for sign in (1, -1):
                est = e + sign * (1 + m0) * complex(*G) + noise
                par = (est * np.conj(e)).real / abs(e)
                for c, v in (("galaxy", i), ("rotation", j), ("sign", sign), ("e1", est.real), ("e2", est.imag),
                             ("weight", np.exp(k * par)), ("fitclass", 0)):
                    rows[c].append(v)
    return {c: np.array(v) for c, v in rows.items()}


def test_paired_weights_remove_the_weights_response_to_shear():
    """Weights that grow as a shear makes a galaxy more elliptical make the weighted mean over-respond; each
    pair's mean weight (``paired_weights``) leaves exactly the estimates' own m, whatever the weights' dependence
    on galaxy, orientation and noise; a star's weight stays 0 and its pair's member keeps its own."""
    from shearfit.calib.bias import paired_weights

    tab = _synthetic_rings()
    n = 40
    rng = np.random.default_rng(0)
    raw, _ = shear_bias(ring_sums(tab, n), G, 10, rng)
    assert np.all(raw[:2] > 0.01 + 0.01)   # the weights' response adds to m
    paired = dict(tab, weight=paired_weights(tab))
    est, _ = shear_bias(ring_sums(paired, n), G, 10, rng)
    np.testing.assert_allclose(est[:2], 0.01, atol=1e-12)
    tab["fitclass"][0] = 1
    w = paired_weights(tab)
    assert w[0] == 0 and w[1] == tab["weight"][1]
    with pytest.raises(shearfit.errors.ShearfitValueError, match="pair"):
        paired_weights(dict(tab, sign=np.ones_like(tab["sign"])))


def test_isotropic_weights_remove_the_weights_response_to_shear():
    """A catalogue's own bins of flux_snr and round_scalelength (which a shear keeps) give every orientation of
    a galaxy the same weight: the weighted mean's m is the estimates' own, while the galaxies' weights still
    differ from bin to bin and the total weight is kept."""
    from shearfit.calib.weights import isotropic_weights

    tab = _synthetic_rings()
    n = 40
    rng = np.random.default_rng(1)
    gal = tab["galaxy"]
    snr = rng.uniform(10, 100, n)[gal]
    r0 = rng.uniform(0.1, 1.0, n)[gal]
    tab.update(flux_snr=snr, round_scalelength=r0)
    raw, _ = shear_bias(ring_sums(tab, n), G, 10, rng)
    assert np.all(raw[:2] > 0.01 + 0.01)
    w = isotropic_weights(tab, n_snr=4, n_size=2)
    est, _ = shear_bias(ring_sums(dict(tab, weight=w), n), G, 10, rng)
    np.testing.assert_allclose(est[:2], 0.01, atol=1e-12)
    assert np.unique(np.round(w, 12)).size == 8
    np.testing.assert_allclose(w.sum(), tab["weight"].sum(), rtol=1e-12)
    # the default: bins of flux_snr alone
    w = isotropic_weights(tab, n_snr=4)
    est, _ = shear_bias(ring_sums(dict(tab, weight=w), n), G, 10, rng)
    np.testing.assert_allclose(est[:2], 0.01, atol=1e-12)
    assert np.unique(np.round(w, 12)).size == 4
    tab["fitclass"][0] = 1
    w = isotropic_weights(tab, n_snr=4, n_size=2)
    assert w[0] == 0 and w[1] > 0
    with pytest.raises(shearfit.errors.ShearfitValueError, match="'flux_snr'"):
        isotropic_weights({k: v for k, v in tab.items() if k != "flux_snr"})


def test_isotropic_bins_hold_a_hundred_galaxies_each():
    """The pipeline's bins of flux_snr: at least 100 galaxies in each, at most 10."""
    from shearfit.calib.weights import isotropic_bins

    assert [isotropic_bins(n) for n in (0, 50, 199, 200, 999, 1000, 10 ** 7)] == [1, 1, 1, 2, 9, 10, 10]
