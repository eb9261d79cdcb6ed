"""Tests of shearfit.engine.priors against the paper's formulas (Miller et al. 2013, App. B).

The reference pdfs below are written out again from the paper, and every
normalisation, CDF and moment is recomputed here by independent quadrature,
so the tests do not reuse the module's own tables.
"""

import subprocess
import sys

import numpy as np
import pytest
from scipy import integrate, special, stats
from scipy.optimize import minimize_scalar

from shearfit.engine import priors
from shearfit.config import FitConfig
from shearfit.errors import ShearfitValueError

CFG = FitConfig()
CFG_MEDIAN = FitConfig(size_prior_scale="median")
N_KS = 20000
P_MIN = 1e-3


# --- reference forms, straight from the paper ---------------------------------

def ref_disk_unnorm(e, cfg=CFG):
    """eq. (edisk) without A."""
    e = np.asarray(e, dtype=float)
    emax, e0, a = cfg.disk_e_max, cfg.disk_e0, cfg.disk_e_a
    return np.where((e >= 0) & (e < emax),
                    e * (1 - np.exp((np.minimum(e, emax) - emax) / a)) / ((1 + e) * np.sqrt(e ** 2 + e0 ** 2)), 0.0)


def ref_bulge_unnorm(e, cfg=CFG):
    """eq. (ebulge) without its constant, on [0, 1)."""
    e = np.asarray(e, dtype=float)
    return np.where((e >= 0) & (e < 1), e * np.exp(-cfg.bulge_e_b * e - cfg.bulge_e_c * e ** 2), 0.0)


def quad_norm(f, lo, hi, points=None):
    val, err = integrate.quad(f, lo, hi, points=points, epsabs=1e-13, epsrel=1e-12, limit=200)
    return val


def ref_cdf(unnorm, x, emax, total):
    """CDF at many x at once: F(x) = x * int_0^1 p(x s) ds / total.

    The substitution e = x s puts every integral on the same fixed interval,
    so one vector-valued adaptive quadrature gives all of them exactly,
    independently of the module's grid tables.
    """
    x = np.clip(np.asarray(x, dtype=float), 0.0, emax)
    val, _ = integrate.quad_vec(lambda s: x * unnorm(x * s), 0.0, 1.0, epsabs=1e-11, epsrel=1e-10)
    return val / total


DISK_TOTAL = quad_norm(ref_disk_unnorm, 0, CFG.disk_e_max, points=[CFG.disk_e0])
BULGE_TOTAL = quad_norm(ref_bulge_unnorm, 0, 1)


def ref_size_scale(mag, cfg):
    r_d = np.exp(-1.145 - 0.269 * (np.asarray(mag, dtype=float) - 23.0))
    if cfg.size_prior_scale == "paper":
        return r_d / 0.833
    return r_d / special.gammaincinv(1.5, 0.5) ** 0.75


def size_cdf(r, mag, cfg):
    alpha = cfg.size_alpha
    return special.gammainc(2 / alpha, (np.asarray(r) / ref_size_scale(mag, cfg)) ** alpha)


# --- 1. normalisation --------------------------------------------------------

def test_disk_pdf_is_the_paper_formula_and_normalised():
    e = np.linspace(0.001, 0.8, 50)
    ratio = priors.disk_e_pdf(e) / ref_disk_unnorm(e)
    np.testing.assert_allclose(ratio, 1 / DISK_TOTAL, rtol=1e-12)
    total = quad_norm(priors.disk_e_pdf, 0, CFG.disk_e_max, points=[CFG.disk_e0])
    assert abs(total - 1) < 1e-6


def test_bulge_pdf_is_the_paper_formula_and_normalised():
    e = np.linspace(0.001, 0.999, 50)
    np.testing.assert_allclose(priors.bulge_e_pdf(e) / ref_bulge_unnorm(e), 1 / BULGE_TOTAL, rtol=1e-12)
    assert abs(quad_norm(priors.bulge_e_pdf, 0, 1) - 1) < 1e-6


@pytest.mark.parametrize("density, emax", [(priors.disk_e_density, CFG.disk_e_max),
                                           (priors.bulge_e_density, 1.0)])
def test_2d_densities_normalised_over_the_plane(density, emax):
    # Polar coordinates; phi is integrated too so that an anisotropy bug shows.
    val, _ = integrate.dblquad(lambda e, phi: density(e * np.cos(phi), e * np.sin(phi)) * e,
                               0, 2 * np.pi, 0, emax, epsabs=1e-11, epsrel=1e-10)
    assert abs(val - 1) < 1e-6


@pytest.mark.parametrize("cfg", [CFG, CFG_MEDIAN], ids=["paper", "median"])
@pytest.mark.parametrize("mag", [18.0, 23.0, 26.5])
def test_size_prior_normalised(cfg, mag):
    val, _ = integrate.quad(lambda r: priors.size_prior_pdf(r, mag, cfg), 0, np.inf, epsabs=1e-12, epsrel=1e-11)
    assert abs(val - 1) < 1e-6


@pytest.mark.parametrize("cfg", [CFG, FitConfig(bulge_fraction_mean=0.3, bulge_fraction_sigma=0.4)],
                         ids=["paper", "offset"])
def test_bulge_fraction_prior_normalised(cfg):
    assert abs(quad_norm(lambda b: priors.bulge_fraction_pdf(b, cfg), 0, 1) - 1) < 1e-6
    # Shape: a Gaussian in B, cut at 0 and 1.
    b = np.array([0.0, 0.25, 0.5, 0.999])
    p = priors.bulge_fraction_pdf(b, cfg)
    g = np.exp(-0.5 * ((b - cfg.bulge_fraction_mean) / cfg.bulge_fraction_sigma) ** 2)
    np.testing.assert_allclose(p / g, p[0] / g[0], rtol=1e-12)
    assert np.all(priors.bulge_fraction_pdf([-1e-9, 1.0, 1.5], cfg) == 0)


def test_normalisation_follows_the_config():
    # Memoisation must key on the constants, not return a stale A.
    cfg = CFG.replace(disk_e_max=0.7)
    total = quad_norm(lambda e: priors.disk_e_pdf(e, cfg), 0, 0.7, points=[cfg.disk_e0])
    assert abs(total - 1) < 1e-6
    assert priors.disk_e_pdf(0.75, cfg) == 0 and priors.disk_e_pdf(0.75) > 0


# --- 2. size prior: median and mode -------------------------------------------

ALPHA = 4 / 3
MEDIAN_OVER_A = special.gammaincinv(2 / ALPHA, 0.5) ** (1 / ALPHA)
MODE_OVER_A = (1 / ALPHA) ** (1 / ALPHA)


def test_size_factors_quoted_in_the_docstring():
    assert MEDIAN_OVER_A == pytest.approx(1.13432, abs=1e-5)
    assert MODE_OVER_A == pytest.approx(0.80593, abs=1e-5)
    assert MEDIAN_OVER_A / 0.833 == pytest.approx(1.3617, abs=1e-4)
    assert 1 / MEDIAN_OVER_A == pytest.approx(0.88159, abs=1e-5)


@pytest.mark.parametrize("cfg", [CFG, CFG_MEDIAN], ids=["paper", "median"])
@pytest.mark.parametrize("mag", [20.0, 23.0, 25.0])
def test_size_prior_median_and_mode(cfg, mag):
    r_d = np.exp(-1.145 - 0.269 * (mag - 23))
    a = priors.size_prior_scale(mag, cfg)
    assert a == pytest.approx(ref_size_scale(mag, cfg), rel=1e-13)

    # Median by quadrature of the module's pdf, solved with the analytic form.
    r_med = a * MEDIAN_OVER_A
    mass, _ = integrate.quad(lambda r: priors.size_prior_pdf(r, mag, cfg), 0, r_med, epsabs=1e-13, epsrel=1e-12)
    assert mass == pytest.approx(0.5, abs=1e-9)
    if cfg.size_prior_scale == "median":
        assert r_med == pytest.approx(r_d, rel=1e-12)
    else:
        # The paper's a = r_d/0.833 puts the median 36 % above r_d.
        assert r_med / r_d == pytest.approx(1.3617, abs=1e-4)

    res = minimize_scalar(lambda r: -priors.size_prior_pdf(r, mag, cfg), bounds=(1e-6 * a, 5 * a),
                          method="bounded", options={"xatol": 1e-10 * a})
    assert res.x == pytest.approx(a * MODE_OVER_A, rel=1e-6)


# --- 3. samplers --------------------------------------------------------------

def test_sample_disk_modulus_ks():
    e = priors.sample_e_modulus("disk", N_KS, np.random.default_rng(1))
    assert e.shape == (N_KS,) and e.min() >= 0 and e.max() < CFG.disk_e_max
    p = stats.kstest(e, lambda x: ref_cdf(ref_disk_unnorm, x, CFG.disk_e_max, DISK_TOTAL)).pvalue
    assert p > P_MIN


def test_sample_bulge_modulus_ks():
    e = priors.sample_e_modulus("bulge", N_KS, np.random.default_rng(2))
    assert e.min() >= 0 and e.max() < 1
    p = stats.kstest(e, lambda x: ref_cdf(ref_bulge_unnorm, x, 1.0, BULGE_TOTAL)).pvalue
    assert p > P_MIN


def test_sample_e_modulus_rejects_unknown_kind():
    with pytest.raises(ShearfitValueError):
        priors.sample_e_modulus("elliptical", 3, np.random.default_rng(0))


@pytest.mark.parametrize("cfg", [CFG, CFG_MEDIAN], ids=["paper", "median"])
def test_sample_size_ks(cfg):
    rng = np.random.default_rng(3)
    r = priors.sample_size(np.full(N_KS, 23.5), rng, cfg)
    assert stats.kstest(r, lambda x: size_cdf(x, 23.5, cfg)).pvalue > P_MIN
    # Mixed magnitudes: the probability-integral transform must be uniform.
    mags = rng.uniform(19, 25, N_KS)
    r = priors.sample_size(mags, rng, cfg)
    assert stats.kstest(size_cdf(r, mags, cfg), "uniform").pvalue > P_MIN


def test_sample_bulge_fraction_ks():
    b = priors.sample_bulge_fraction(N_KS, np.random.default_rng(4))
    assert b.min() >= 0 and b.max() < 1
    cdf = stats.truncnorm(a=0, b=10, loc=0, scale=0.1).cdf  # truncation at B = 1 is 10 sigma
    assert stats.kstest(b, cdf).pvalue > P_MIN


def test_sample_population():
    rng = np.random.default_rng(5)
    mags = rng.uniform(20, 25, N_KS)
    pop = priors.sample_population(mags, rng)
    assert len(pop) == N_KS
    np.testing.assert_array_equal(pop["mag"], mags)

    # Bulge-dominated fraction within 4 binomial sigma of f_B.
    fb = CFG.bulge_population_fraction
    nb = int(pop.is_bulge.sum())
    assert abs(nb - fb * N_KS) < 4 * np.sqrt(N_KS * fb * (1 - fb))

    assert np.all(pop.bulge_fraction[pop.is_bulge] == 1.0)
    bd = pop.bulge_fraction[~pop.is_bulge]
    assert bd.min() >= 0 and bd.max() < 1
    assert stats.kstest(bd, stats.truncnorm(a=0, b=10, loc=0, scale=0.1).cdf).pvalue > P_MIN

    emod = np.hypot(pop.e1, pop.e2)
    disk_cdf = lambda x: ref_cdf(ref_disk_unnorm, x, CFG.disk_e_max, DISK_TOTAL)  # noqa: E731
    bulge_cdf = lambda x: ref_cdf(ref_bulge_unnorm, x, 1.0, BULGE_TOTAL)  # noqa: E731
    assert stats.kstest(emod[~pop.is_bulge], disk_cdf).pvalue > P_MIN
    assert stats.kstest(emod[pop.is_bulge], bulge_cdf).pvalue > P_MIN

    # e = |e| exp(2 i theta), theta uniform on [0, pi): 2 theta uniform on the circle.
    two_theta = np.mod(np.arctan2(pop.e2, pop.e1), 2 * np.pi)
    assert stats.kstest(two_theta / (2 * np.pi), "uniform").pvalue > P_MIN

    assert stats.kstest(size_cdf(pop.scalelength, mags, CFG), "uniform").pvalue > P_MIN


def test_sample_population_reproducible():
    mags = np.linspace(20, 25, 50)
    a = priors.sample_population(mags, np.random.default_rng(9))
    b = priors.sample_population(mags, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)


# --- 4. population sigma vs the paper's sigma_pop = 0.255 ---------------------

def test_population_sigma_against_paper():
    sig = priors.population_sigma()

    # Independent second moments.
    m2_disk = quad_norm(lambda e: e ** 2 * ref_disk_unnorm(e), 0, CFG.disk_e_max, points=[CFG.disk_e0]) / DISK_TOTAL
    m2_bulge = quad_norm(lambda e: e ** 2 * ref_bulge_unnorm(e), 0, 1) / BULGE_TOTAL
    fb = CFG.bulge_population_fraction
    assert sig.disk == pytest.approx(np.sqrt(m2_disk / 2), rel=1e-9)
    assert sig.bulge == pytest.approx(np.sqrt(m2_bulge / 2), rel=1e-9)
    assert sig.mixed == pytest.approx(np.sqrt(((1 - fb) * m2_disk + fb * m2_bulge) / 2), rel=1e-9)
    # What the paper's priors give (quoted in the population_sigma docstring):
    # disk 0.256203, mixed (f_B = 0.1) 0.253169, bulge 0.224016.
    assert (sig.disk, sig.mixed, sig.bulge) == pytest.approx((0.256203, 0.253169, 0.224016), abs=1e-6)

    paper = CFG.sigma_pop  # 0.255
    # Tolerance. The paper does not say whether its 0.255 is the disk-only or
    # the mixed population, nor how it integrated. A tolerance that can tell
    # the two definitions apart must be below half their separation:
    tol = abs(sig.disk - sig.mixed) / 2  # = 0.00152 (0.6 %)
    # and it must exceed what rounding alone can explain: half a unit in the
    # last quoted digit of 0.255, plus the effect on sigma of rounding each
    # fitted prior constant to its quoted digits (finite differences):
    step = {"disk_e_max": 0.0005, "disk_e0": 0.00005, "disk_e_a": 0.00005}
    d_param = sum(abs(priors.population_sigma(CFG.replace(**{k: getattr(CFG, k) + h})).disk - sig.disk)
                  for k, h in step.items())
    rounding = 0.0005 + d_param  # = 0.00068
    assert rounding < tol

    # Finding: the disk-only prior matches best, within the tolerance
    # (0.256203 - 0.255 = +0.0012, +0.47 %); the mixed population is 0.0018
    # (-0.72 %) below and outside it; the bulge prior alone is 12 % off.
    off = {k: abs(v - paper) for k, v in sig._asdict().items()}
    assert min(off, key=off.get) == "disk"
    assert off["disk"] < tol
    assert off["mixed"] > tol
    # Neither reproduces 0.255 to the paper's quoted precision: the disk value
    # would round to 0.256. The residual 0.0005 beyond the rounding budget is
    # what a coarser numerical integration or slightly different fitted
    # constants (e.g. e_max = 0.8003 instead of 0.804) would produce.
    assert off["disk"] > rounding


# --- 5. 2D density at e = 0 ----------------------------------------------------

def test_disk_density_finite_and_continuous_at_zero():
    emax, e0, a = CFG.disk_e_max, CFG.disk_e0, CFG.disk_e_a
    # lim_{e->0} p(e)/(2 pi e) = (1 - exp(-emax/a)) / (2 pi e0) / total
    limit = (1 - np.exp(-emax / a)) / (2 * np.pi * e0) / DISK_TOTAL
    at0 = priors.disk_e_density(0.0, 0.0)
    assert np.isfinite(at0)
    assert at0 == pytest.approx(limit, rel=1e-12)
    # Continuity: the density's slope at 0 is O(1/e0) relative, so e = 1e-9
    # may differ by ~1e-9; 1e-7 leaves room without hiding a jump.
    for e1, e2 in [(1e-9, 0.0), (0.0, 1e-9), (-7e-10, 7e-10)]:
        assert priors.disk_e_density(e1, e2) == pytest.approx(limit, rel=1e-7)
    # The 1D pdf divided by 2 pi e agrees away from zero.
    e = np.array([1e-6, 0.01, 0.3])
    np.testing.assert_allclose(priors.disk_e_density(e, 0 * e), priors.disk_e_pdf(e) / (2 * np.pi * e), rtol=1e-12)


def test_bulge_density_finite_and_continuous_at_zero():
    limit = 1 / (2 * np.pi * BULGE_TOTAL)
    assert priors.bulge_e_density(0.0, 0.0) == pytest.approx(limit, rel=1e-12)
    assert priors.bulge_e_density(1e-9, 0.0) == pytest.approx(limit, rel=1e-7)


# --- shapes, supports, flux prior, laziness ------------------------------------

def test_vectorised_shapes_and_support():
    assert np.ndim(priors.disk_e_pdf(0.3)) == 0
    assert priors.disk_e_pdf(np.zeros((3, 4))).shape == (3, 4)
    assert priors.disk_e_density(np.zeros((2, 1)), np.zeros(5)).shape == (2, 5)
    assert priors.size_prior_pdf(np.linspace(0, 2, 7)[:, None], np.array([21.0, 24.0])).shape == (7, 2)
    assert np.all(priors.disk_e_pdf([-0.1, CFG.disk_e_max, 0.9]) == 0)
    assert np.all(priors.bulge_e_pdf([-0.1, 1.0, 1.3]) == 0)
    assert priors.disk_e_density(0.6, 0.6) == 0  # |e| = 0.85 > e_max
    assert priors.size_prior_pdf(-0.1, 23.0) == 0
    assert np.isnan(priors.disk_e_pdf(np.nan))


def test_log_flux_prior():
    S = np.array([0.5, 1.0, 10.0])
    np.testing.assert_allclose(priors.log_flux_prior(S), -2 * np.log(S), rtol=1e-15)
    assert priors.log_flux_prior(1.0, FitConfig(flux_prior_slope=1.5)) == 0
    assert np.all(priors.log_flux_prior([0.0, -3.0]) == -np.inf)


def test_nothing_computed_at_import():
    code = ("import shearfit.engine.priors as p; "
            "print(p._disk_norm.cache_info().currsize + p._bulge_norm.cache_info().currsize "
            "+ p._modulus_cdf_table.cache_info().currsize)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "0"
