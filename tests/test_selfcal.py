"""Self-calibration (FitConfig.self_calibration): the estimator's bias measured on noise-free images of the fit's
own model and removed (shearfit.engine.measure)."""

import numpy as np
import pytest

import shearfit
from shearfit.config import as_config
from shearfit.engine import measure as M
from shearfit.simulate.stamps import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr

PIX = 0.187
J = PIX * np.eye(2)


def _setup(seed=7, n=7):
    rng = np.random.default_rng(seed)
    psfs = [moffat_psf(rng.uniform(0.55, 0.75), rng.uniform(2.5, 4.5), *rng.uniform(-0.07, 0.07, 2)) for _ in range(n)]
    offs = rng.uniform(-0.5, 0.5, (n, 2))
    return psfs, offs, [draw_psf_image(p, J, size=48) for p in psfs]


def _obs(r, e, g, psfs, offs, pims, snr=150.0, sigma=None, nominal_shift=(0.0, 0.0)):
    gal = galaxy_profile(r, 0.05, e.real, e.imag, flux=1000.0, g1=g[0], g2=g[1])
    ims = [draw_stamp(gal, p, J, o) for p, o in zip(psfs, offs)]
    sigma = sigma or noise_for_snr(ims, snr)
    return [shearfit.Observation(image=im, weight=np.full(im.shape, sigma ** -2), psf=pi, jacobian=J,
                                 offset=np.asarray(o) + nominal_shift) for im, pi, o in zip(ims, pims, offs)], sigma


def _ring_m(r, e, cfg, setup):
    """m of a noise-free 4-orientation ring at shear +-(0.03, -0.02) (weighted means)."""
    g = np.array([0.03, -0.02])
    mean = {}
    sigma = None
    for sign in (1, -1):
        es = []
        for k in range(4):
            obs, sigma = _obs(r, e * np.exp(1j * np.pi * k / 2), sign * g, *setup, sigma=sigma)
            res = shearfit.measure_object(obs, mag=24.0, config=cfg)
            es.append((res.e1, res.e2, res.weight))
        es = np.array(es)
        mean[sign] = np.average(es[:, :2], weights=es[:, 2], axis=0)
    return (mean[1] - mean[-1]) / (2 * g) - 1


def test_self_calibration_removes_a_small_galaxys_over_response():
    """A noise-free r = 0.15" galaxy (weights of SNR 150): the likelihood mean over-responds to shear
    (benchmarks/small_galaxy_bias.py: m = +0.016); its self-calibrated estimate responds within 3e-3 (+0.001
    when written), as does a resolved r = 0.4" one, whose m2 of -0.010 is the sampling lattice's."""
    setup = _setup()
    raw = _ring_m(0.15, 0.35, {}, setup)
    cal = _ring_m(0.15, 0.35, {"self_calibration": True}, setup)
    assert np.all(raw > 0.01)
    assert np.all(np.abs(cal) < 3e-3)
    big = _ring_m(0.4, 0.35, {"self_calibration": True}, setup)
    assert np.all(np.abs(big) < 3e-3)


def test_model_image_at_the_fitted_position():
    """The model a self-calibration measures is drawn where the fit found the galaxy: with every nominal
    position 0.4 pixel off, the model at the true parameters matches GalSim's image to a small fraction of its
    peak, and the model drawn at the nominal position (the fit's shift ignored) does not."""
    psfs, offs, pims = _setup(n=3)
    e = complex(0.3, -0.1)
    obs, _ = _obs(0.3, e, (0, 0), psfs, offs, pims, snr=300, nominal_shift=(0.4, -0.25))
    cfg = as_config({})
    res, plan = M._measure(obs, 23.0, cfg, False)
    assert np.hypot(*plan.shift) > 0.05       # arcsec: the fit moved the model
    params = (e.real, e.imag, 0.3, 0.05, 1000.0)
    models = M.model_observations(obs, plan, params, cfg)
    for o, m in zip(obs, models):
        assert np.abs(m.image - o.image).max() < 0.01 * o.image.max()
    unmoved = [shearfit.engine.model.render_object(o, *params, cfg) for o in obs]
    assert max(np.abs(u - o.image).max() / o.image.max() for u, o in zip(unmoved, obs)) > 0.05


def test_model_image_is_the_components_transforms_on_the_moved_modes():
    """model_observations makes the phase once per plan, rho^2 once for both components and the fold by bincount:
    the same pixels, to the bit, as model_ft of each component on the modes moved to the fit's position, with a
    bulge of the disk's size and of its own (bulge_size_ratio), and a second model on the same plan."""
    from dataclasses import replace

    from shearfit.engine.model import model_ft
    from shearfit.engine.profiles import de_vaucouleurs, exponential_disk

    psfs, offs, pims = _setup(n=3)
    obs, _ = _obs(0.3, complex(0.3, -0.1), (0, 0), psfs, offs, pims, snr=300, nominal_shift=(0.4, -0.25))
    for ratio in (1.0, 0.6):
        cfg = as_config({"bulge_size_ratio": ratio})
        _, plan = M._measure(obs, 23.0, cfg, False)
        du, dv = plan.shift
        for params in ((0.3, -0.1, 0.3, 0.4, 1000.0), (-0.5, 0.2, 0.2, 0.0, 800.0)):
            e1, e2, r, b, flux = params
            for o, ex, m in zip(obs, plan.exposures, M.model_observations(obs, plan, params, cfg)):
                moved = replace(ex, transfer=ex.transfer * np.exp(-1j * (ex.kx * du + ex.ky * dv)))
                F = (1.0 - b) * model_ft(moved, exponential_disk(cfg.truncation), e1, e2, r)
                if b != 0:
                    F = F + b * model_ft(moved, de_vaucouleurs(cfg.truncation), e1, e2, r * ratio)
                ref = np.fft.fftshift(np.fft.irfft2(F, s=ex.shape)) * flux
                assert np.array_equal(m.image, ref)


def test_self_calibration_leaves_a_resolved_estimate_and_reports_its_correction():
    """A resolved galaxy (r = 0.3", SNR 100): the correction is tiny, reported in selfcal_de, and the response
    estimates (radial, tangential) are close to 1 (1.00, 1.00 when written); without the setting, no correction
    is made and nothing else changes."""
    psfs, offs, pims = _setup(n=3)
    obs, _ = _obs(0.3, complex(0.2, 0.1), (0, 0), psfs, offs, pims, snr=100)
    plain = shearfit.measure_object(obs, mag=22.0)
    cal = shearfit.measure_object(obs, mag=22.0, config={"self_calibration": True})
    assert plain.selfcal_de is None and plain.selfcal_response is None
    de = np.array(cal.selfcal_de)
    assert np.hypot(*de) < 3e-3
    assert (cal.e1, cal.e2) == pytest.approx((plain.e1 - de[0], plain.e2 - de[1]), abs=1e-12)
    assert cal.selfcal_response == pytest.approx((1.0, 1.0), abs=0.03)
    assert (cal.e_var, cal.weight, cal.fitclass) == (plain.e_var, plain.weight, plain.fitclass)


def test_a_model_without_estimate_fails_the_object(monkeypatch):
    """If the model's image gives no estimate, the object is not left uncorrected among corrected ones: it
    becomes a failed fit (fitclass -2) of weight 0, with a message."""
    psfs, offs, pims = _setup(n=3)
    obs, _ = _obs(0.3, complex(0.2, 0.1), (0, 0), psfs, offs, pims, snr=100)
    real = M._measure
    calls = []

    def fake(o, mag, cfg, return_samples, plan=None, **kw):
        calls.append(plan is None)
        if plan is None:
            return real(o, mag, cfg, return_samples, plan=plan, **kw)
        return shearfit.FitResult(), None

    monkeypatch.setattr(M, "_measure", fake)
    res = shearfit.measure_object(obs, mag=22.0, config={"self_calibration": True})
    assert calls[0] and not calls[-1]
    assert res.fitclass == shearfit.errors.FITCLASS_FIT_FAILED and res.weight == 0.0
    assert "self-calibration" in res.message


def test_more_newton_steps_converge_on_the_models_solution():
    """self_calibration_steps: for a noise-free r = 0.1-0.11" galaxy at |e| ~ 0.5 one Newton step stops 1.3-1.5e-3
    from the solution of f(e) = e_hat (the response found towards e = 0 is below the one there); further steps
    with the same responses converge on it (4 and 6 steps agree to 1e-6 when written)."""
    setup = _setup()
    for r, e in [(0.1, 0.45 + 0.2j), (0.11, 0.52j)]:
        obs, _ = _obs(r, complex(e), (0.03, -0.02), *setup, snr=150)
        out = {}
        for k in (1, 4, 6):
            res = shearfit.measure_object(obs, mag=24.0, config={"self_calibration": True,
                                                                 "self_calibration_steps": k})
            out[k] = np.array([res.e1, res.e2])
        assert np.hypot(*(out[1] - out[6])) > 5e-4
        assert np.hypot(*(out[4] - out[6])) < 1e-5
    for bad in (0, 21):
        with pytest.raises(shearfit.errors.ShearfitValueError, match="self_calibration_steps"):
            as_config({"self_calibration_steps": bad})


def _fake_solve(monkeypatch, F, e_hat, steps, sigma_e=0.02, **settings):
    """_self_calibrate on a noise-free estimator F(e) of our own (the model images and their fits replaced):
    returns the result and the ellipticities F was evaluated at."""
    seen = []
    monkeypatch.setattr(M, "model_observations", lambda obs, plan, params, cfg: np.array(params[:2]))
    def fake(models, mag, cfg, return_samples, plan=None, **kw):
        seen.append(np.array(models))
        f = F(np.array(models))
        return shearfit.FitResult(e1=float(f[0]), e2=float(f[1])), None
    monkeypatch.setattr(M, "_measure", fake)
    res = shearfit.FitResult(e1=e_hat[0], e2=e_hat[1], e_var=sigma_e ** 2, scalelength=0.1, bulge_fraction=0.0,
                             model_flux=1.0, fitclass=0)
    M._self_calibrate(None, 24.0, as_config({"self_calibration": True, "self_calibration_steps": steps, **settings}),
                      res, plan=object())
    return res, seen


def _saturating(e):
    """An estimator that saturates: |f| < 0.3 at every |e| (a broad likelihood whose noise-free estimate cannot
    reach a data estimate of |e_hat| >= 0.3), turning with the galaxy."""
    a = np.hypot(*e)
    return e / a * 0.3 * np.tanh(a / 0.3) if a > 0 else e


def test_further_steps_solve_and_stop_where_the_solve_does_not_contract(monkeypatch):
    """The further Newton steps are damped by how well the last one contracted |f(e) - e_hat| (SELFCAL_DAMPING):
    an estimator whose solution the steps approach fast (f(e) = e - 0.4 e |e|^2) is solved to 1e-6 in 4 steps;
    one that saturates short of the data's estimate (e_hat 0.35: no solution) is not carried towards the model's
    limit, as undamped steps carry it."""
    e_hat = np.array([0.3, 0.25])

    def solvable(e):
        return e - 0.4 * e * np.dot(e, e)

    res, seen = _fake_solve(monkeypatch, solvable, e_hat, 4)
    assert res.selfcal_steps == 4 and len(seen) == 2 + 3
    assert np.hypot(*(solvable(np.array([res.e1, res.e2])) - e_hat)) < 1e-6

    e_hat = np.array([0.3, -0.18])   # |e_hat| 0.35
    res, seen = _fake_solve(monkeypatch, _saturating, e_hat, 6)
    assert res.selfcal_steps < 6 and len(seen) < 2 + 5
    assert np.hypot(res.e1, res.e2) < as_config({}).model_e_limit - 0.3
    # without the damping the same steps carry it to the model's limit
    monkeypatch.setattr(M, "SELFCAL_DAMPING", (1e9, 1e9 + 1))
    far, _ = _fake_solve(monkeypatch, _saturating, e_hat, 6)
    assert np.hypot(far.e1, far.e2) > as_config({}).model_e_limit - 1e-9


def test_further_steps_move_smoothly_with_the_data(monkeypatch):
    """The damped solve's result is a continuous function of the data's estimate: across |e_hat| 0.15-0.29 of the
    saturating estimator, where the steps' contraction goes from fast to none, the result's slope stays below
    that of the exact inverse (1 / f' <= 6.4 there). A rule that stops the steps where the contraction crosses one
    value (the damping's ramp shrunk to a step at 0.5) jumps: two members of a +g / -g pair on either side of it
    differ by the unconverged residual."""
    grid = np.linspace(0.15, 0.29, 701)

    def slope():
        out = [_fake_solve(monkeypatch, _saturating, np.array([a, 0.0]), 4, sigma_e=0.08)[0].e1 for a in grid]
        return np.max(np.abs(np.diff(out)) / np.diff(grid))

    assert slope() < 6.4
    monkeypatch.setattr(M, "SELFCAL_DAMPING", (0.5 - 1e-9, 0.5))
    assert slope() > 30


def test_min_response_bounds_the_radial_correction(monkeypatch):
    """self_calibration_min_response: an estimator that responds radially with slope 0.3 (an estimate pulled in
    towards a saturating |e|, as small galaxies' at high |e|; tangentially it turns with the galaxy) and is linear
    there: with the bound at 0.5 one step corrects 0.3 / 0.5 of the bias and leaves the rest, with the bound below
    0.3 one step solves it exactly. Settings outside (0, 1] are refused."""
    e_true = np.array([0.54, 0.42])   # |e| 0.684
    u = e_true / np.hypot(*e_true)

    def pulled(e):   # radially f = 0.62 + 0.3 (|e| - 0.684), along the galaxy's own direction
        a = np.hypot(*e)
        return e / a * (0.62 + 0.3 * (a - np.hypot(*e_true)))

    e_hat = pulled(e_true)
    bounded, _ = _fake_solve(monkeypatch, pulled, e_hat, 1, sigma_e=0.08)
    free, _ = _fake_solve(monkeypatch, pulled, e_hat, 1, sigma_e=0.08, self_calibration_min_response=0.2)
    assert bounded.selfcal_response[0] == pytest.approx(0.3, abs=1e-9)
    short = np.dot(e_true - np.array([bounded.e1, bounded.e2]), u)
    assert short == pytest.approx((1 - 0.3 / 0.5) * np.dot(e_true - e_hat, u), rel=1e-6)
    assert np.hypot(free.e1 - e_true[0], free.e2 - e_true[1]) < 1e-9
    for bad in (0, -0.1, 1.2):
        with pytest.raises(shearfit.errors.ShearfitValueError, match="self_calibration_min_response"):
            as_config({"self_calibration_min_response": bad})


def test_corrected_e_limit_lets_the_estimate_go_on_beyond_the_models(monkeypatch):
    """corrected_e_limit: an estimator of slope 0.85 along |e| (f(0.98) = 0.833) and a data estimate of 0.9, whose
    solution (1.059) lies beyond the models' limit model_e_limit = 0.98. By default the estimate stops on the limit;
    with corrected_e_limit = 2 it goes on beyond it along the measured response (the step from the limit, along f's
    last secant, damped as every further step is), while every noise-free fit stays within the limit; a lower
    corrected_e_limit is kept."""
    def linear(e):
        return 0.85 * e

    e_hat = np.array([0.9 * np.cos(0.4), 0.9 * np.sin(0.4)])
    res, seen = _fake_solve(monkeypatch, linear, e_hat, 4)
    assert np.hypot(res.e1, res.e2) == pytest.approx(0.98, abs=1e-12)
    res, seen = _fake_solve(monkeypatch, linear, e_hat, 4, corrected_e_limit=2.0)
    a = np.hypot(res.e1, res.e2)
    assert 0.99 < a <= 0.9 / 0.85 + 1e-9
    assert np.arctan2(res.e2, res.e1) == pytest.approx(0.4, abs=1e-9)   # radial only: f turns with the galaxy
    assert max(np.hypot(*e) for e in seen) <= 0.98 + 1e-12
    res, _ = _fake_solve(monkeypatch, linear, e_hat, 4, corrected_e_limit=1.0)
    assert np.hypot(res.e1, res.e2) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(shearfit.errors.ShearfitValueError, match="corrected_e_limit"):
        as_config({"corrected_e_limit": 0.0})


def test_a_step_that_overshoots_a_solution_brackets_it(monkeypatch):
    """An estimator that flattens beyond its knee (f = 0.63 tanh(|e| / 0.25) along |e|, turning with the galaxy: a
    broad likelihood's), whose data estimate lies beyond the knee, f(0.39) = 0.577: the first step, by the
    response found there (0.11 at e_hat), overshoots the solution to |e| 0.24, where the residual is larger and of the
    other sign. The damping alone stops the solve there; the iterates on the two sides bracket the solution, and the
    further steps (SELFCAL_BRACKETS) solve it within the bracket."""
    a_true, angle = 0.39, 0.7
    u = np.array([np.cos(angle), np.sin(angle)])

    def knee(e):
        a = np.hypot(*e)
        return e / a * 0.63 * np.tanh(a / 0.25)

    e_hat = knee(a_true * u)
    res, seen = _fake_solve(monkeypatch, knee, e_hat, 6, sigma_e=0.18, self_calibration_min_response=0.1)
    assert np.hypot(res.e1, res.e2) == pytest.approx(a_true, abs=2e-3)
    assert np.arctan2(res.e2, res.e1) == pytest.approx(angle, abs=1e-9)
    assert max(np.hypot(*e) for e in seen) <= np.hypot(*e_hat) + 1e-12   # every iterate within the bracket
    monkeypatch.setattr(M, "SELFCAL_BRACKETS", False)
    stopped, _ = _fake_solve(monkeypatch, knee, e_hat, 6, sigma_e=0.18, self_calibration_min_response=0.1)
    assert np.hypot(stopped.e1, stopped.e2) < 0.3 and stopped.selfcal_steps == 1
