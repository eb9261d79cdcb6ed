"""Appendix C: the Gaussian model of noise bias against GalSim and against its own Monte Carlo."""

import numpy as np
import pytest
from astropy.io import fits

galsim = pytest.importorskip("galsim")

from shearfit.calib import noisebias as nb  # noqa: E402
from shearfit.app.cli import main  # noqa: E402


@pytest.mark.parametrize("e", [(0.3, 0.0), (0.1, -0.4), (0.0, 0.3), (-0.55, 0.2)])
def test_covariance_is_galsims_gaussian(e):
    """C(e, s) of App. C is the second-moment matrix of the Gaussian GalSim draws for it."""
    n = 240
    im = nb._galsim_gaussian(galsim, e, 3.0).drawImage(nx=n, ny=n, scale=1.0, method="no_pixel").array
    c = np.arange(n) - (n - 1) / 2
    X, Y = np.meshgrid(c, c, indexing="xy")
    w = im / im.sum()
    M = np.array([[np.sum(w * X * X), np.sum(w * X * Y)], [np.sum(w * X * Y), np.sum(w * Y * Y)]])
    np.testing.assert_allclose(M, nb.gaussian_cov(*e, 3.0), atol=1e-5)
    # axis ratio (1 - e)/(1 + e): e = (a - b)/(a + b)
    lam = np.linalg.eigvalsh(M)
    ee = np.hypot(*e)
    assert np.sqrt(lam[0] / lam[1]) == pytest.approx((1 - ee) / (1 + ee), rel=1e-5)


def test_expected_loglike_peaks_at_the_galaxy():
    e1, e2 = nb.ellipticity_grid(0.01)
    ll = nb.expected_loglike(e1, e2, 3.0, (0.3, 0.0), 3.0, (0.0, 0.3), 3.0, 20.0)
    k = np.argmax(ll)
    assert (e1[k], e2[k]) == pytest.approx((0.3, 0.0), abs=1e-9)
    assert ll[k] == pytest.approx(20.0 ** 2 / 2)
    # the surface is skewed towards the PSF and towards e = 0: the mean is pulled from the maximum
    m1, m2 = nb.likelihood_mean(ll, e1, e2)
    assert m1 < 0.29 and m2 > 0


def test_monte_carlo_surface_matches_the_expectation():
    """Mean log L of noisy GalSim images equals the analytic <log L> + 1/2, point by point."""
    rng = np.random.default_rng(3)
    e1, e2 = nb.ellipticity_grid(0.05, 0.6)
    models = nb._model_images(e1, e2, 3.0, (0.0, 0.1), 3.0, 96)
    mm = np.sum(models ** 2, axis=1)
    prof = galsim.Convolve(nb._galsim_gaussian(galsim, (0.2, -0.1), 3.0),
                           nb._galsim_gaussian(galsim, (0.0, 0.1), 3.0))
    clean = prof.drawImage(nx=96, ny=96, scale=1.0, method="no_pixel").array
    sigma = np.sqrt(np.sum(clean ** 2)) / 15.0
    ll = nb._surfaces(clean, sigma, models, mm, 400, rng)
    ana = nb.expected_loglike(e1, e2, 3.0, (0.2, -0.1), 3.0, (0.0, 0.1), 3.0, 15.0) + 0.5
    # the surfaces' common offset fluctuates (and does not matter): compare differences from the maximum
    k = int(np.argmax(ana))
    d = ll.reshape(400, 2, -1).mean(axis=1)
    d = d - d[:, k:k + 1]
    err = d.std(axis=0) / np.sqrt(400)
    near = (ana > ana[k] - 20) & (np.arange(ana.size) != k)
    pull = (d.mean(axis=0) - (ana - ana[k]))[near] / err[near]
    assert np.max(np.abs(pull)) < 5
    assert abs(np.mean(pull)) < 2


def test_population_bias_limits_and_signs():
    c = nb.population_bias([10.0, 1000.0], n_angles=8, step=0.02)
    assert c.one_plus_m[1] == pytest.approx(1.0, abs=1e-3)
    assert abs(c.xi_psf_gal[1]) < 1e-6
    # noise bias at SNR 10: towards zero, and towards the PSF (sec. 7, App. C)
    assert c.one_plus_m[0] < 0.9
    assert c.xi_psf_gal[0] > 1e-4


def test_monte_carlo_bias_agrees_with_the_expectation():
    mc = nb.monte_carlo_bias([10.0], n_angles=4, n_pairs=60, n_groups=6, seed=2)
    pull = (mc["m"] - mc["m_analytic"]) / mc["m_err"]
    assert abs(pull[0]) < 4
    assert mc["m"][0] < 0.9


def test_cli_writes_figures_and_table(tmp_path, capsys):
    assert main(["noisebias", "--out", str(tmp_path), "--snr", "20", "--pairs", "12"]) == 0
    out = capsys.readouterr().out
    assert "1+m" in out and "Monte Carlo" in out
    for name in ("contours.png", "bias.png", "noisebias.fits"):
        assert (tmp_path / name).stat().st_size > 0
    with fits.open(tmp_path / "noisebias.fits") as h:
        assert h["CURVE"].data["one_plus_m"][-1] == pytest.approx(1.0, abs=2e-3)
        assert h["MONTECARLO"].data["snr"][0] == 20.0
    assert main(["noisebias", "--out", str(tmp_path), "--pairs", "3"]) != 0
