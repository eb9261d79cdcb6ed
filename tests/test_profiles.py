"""Tests of shearfit.engine.profiles: truncated Sersic profiles and their tabulated Hankel transforms.

R(k) = 2 pi int_0^T I(r) J0(k r) r dr / flux is checked against (a) the
module's own slow quadrature, (b) an independent brute-force real-axis
quadrature written here, (c) GalSim, and (d) closed forms.
"""

import pickle

import numpy as np
import pytest
from numpy.polynomial.legendre import leggauss
from scipy import integrate, optimize, special

from shearfit.errors import ShearfitValueError
from shearfit.engine.profiles import RadialProfile, de_vaucouleurs, exponential_disk, sersic

T = 4.5
B4 = special.gammaincinv(8, 0.5)  # 7.66925: r = 1 is the untruncated half-light radius


@pytest.fixture(scope="module")
def profiles():
    return {"exponential": exponential_disk(), "devaucouleurs": de_vaucouleurs(), "sersic2.5": sersic(2.5)}


@pytest.fixture(params=["exponential", "devaucouleurs", "sersic2.5"])
def profile(request, profiles):
    return profiles[request.param]


def brute_force_ft(k, n, b, trunc, radians_per_panel=1.0, order=20):
    """Independent reference: real-axis composite Gauss-Legendre quadrature.

    Integrates in t = r^(1/m), m = max(n, 1), so that exp(-b r^(1/n)) is
    smooth at the cusp, with panels of equal J0 phase (uniform in r) sized
    for the largest k, plus panels halving towards t = 0. Costs ~ k T nodes
    per k, which is why the module does not do this at large k.
    """
    k = np.atleast_1d(np.asarray(k, dtype=float))
    m = max(n, 1.0)
    n_pan = int(np.ceil(k.max() * trunc / radians_per_panel)) + 40
    edges_r = np.linspace(0.0, trunc, n_pan + 1)
    edges = np.unique(np.concatenate([edges_r ** (1 / m), edges_r[1] ** (1 / m) * 0.5 ** np.arange(1, 25)]))
    x, w = leggauss(order)
    a, c = edges[:-1, None], edges[1:, None]
    t = (0.5 * (c - a) * x + 0.5 * (a + c)).ravel()
    wt = (0.5 * (c - a) * w).ravel()
    r = t ** m
    g = m * t ** (2 * m - 1) * np.exp(-b * r ** (1 / n)) * wt  # r I(r) dr
    return np.array([special.j0(kk * r) @ g for kk in k]) / g.sum()


# ---------------------------------------------------------------------------
# 1. normalisation


def test_ft_at_zero_is_one(profile):
    assert profile.ft(0.0) == 1.0
    assert profile.ft_rho2(np.zeros(3)).tolist() == [1.0, 1.0, 1.0]
    assert profile.ft_quadrature(0.0) == pytest.approx(1.0, abs=1e-13)


def test_surface_brightness_has_unit_flux(profile):
    # 2 pi int_0^T I(r) r dr; substituting r = t^4 keeps the de Vaucouleurs
    # cusp from costing quad its accuracy.
    def integrand(t):
        r = t ** 4
        return 2 * np.pi * profile.surface_brightness(r) * r * 4 * t ** 3

    flux, _ = integrate.quad(integrand, 0.0, T ** 0.25, epsabs=1e-13, epsrel=1e-12, limit=200)
    assert flux == pytest.approx(1.0, abs=1e-10)


def test_surface_brightness_shape(profiles):
    exp, dev = profiles["exponential"], profiles["devaucouleurs"]
    r = np.array([0.0, 0.5, 2.0, 4.49, 4.5, 6.0])
    # Truncated exponential: flux int_0^T e^-r 2 pi r dr = 2 pi (1 - (1+T) e^-T).
    expected = np.exp(-r) / (2 * np.pi * (1 - (1 + T) * np.exp(-T)))
    expected[r >= T] = 0.0
    np.testing.assert_allclose(exp.surface_brightness(r), expected, rtol=1e-14)
    ratio = dev.surface_brightness(1.0) / dev.surface_brightness(0.0)
    assert ratio == pytest.approx(np.exp(-B4), rel=1e-14)
    assert exp.surface_brightness(r.reshape(2, 3)).shape == (2, 3)


# ---------------------------------------------------------------------------
# 2. table against quadrature


def test_table_matches_quadrature_off_grid(profile):
    rng = np.random.default_rng(12345)
    # 100 anywhere in [0, rho_max], 100 in [0, 60] where R curves most;
    # exact node abscissae have probability zero.
    k = np.concatenate([rng.uniform(0, profile.rho_max, 100), rng.uniform(0, 60, 100)])
    assert not np.isin(k * k, profile.rho2_nodes).any()
    err = np.abs(profile.ft(k) - profile.ft_quadrature(k))
    assert err.max() < 2e-6


def test_table_worst_case_between_nodes(profile):
    # The interpolation error peaks inside intervals: probe the quarter,
    # middle and three-quarter points (in rho2) of 300 random intervals.
    rng = np.random.default_rng(7)
    nodes = profile.rho2_nodes
    i = rng.integers(0, nodes.size - 1, 300)
    frac = np.array([0.25, 0.5, 0.75])[:, None]
    k = np.sqrt(nodes[i] + frac * (nodes[i + 1] - nodes[i])).ravel()
    err = np.abs(profile.ft(k) - profile.ft_quadrature(k))
    assert err.max() < 2e-6


def test_negligible_beyond_rho_max(profile):
    assert profile.rho_max >= 400
    # Sample 10 points per oscillation period 2 pi / T of the truncation tail.
    k = np.arange(profile.rho_max, 1.5 * profile.rho_max, 0.1 * 2 * np.pi / T)
    assert np.abs(profile.ft_quadrature(k)).max() < 1e-6
    assert np.all(profile.ft(k[1:]) == 0.0)


@pytest.mark.parametrize("name, n, b", [("exponential", 1.0, 1.0), ("devaucouleurs", 4.0, B4),
                                        ("sersic2.5", 2.5, special.gammaincinv(5, 0.5))])
def test_quadrature_matches_brute_force(profiles, name, n, b):
    # The module computes large-k values on complex rays (contour deformation);
    # check that against plain real-axis quadrature, across the switch
    # (k T = 45) and far into the oscillating tail.
    k = np.array([0.3, 3.0, 9.9, 10.1, 17.3, 44.4, 123.4, 1000.7, 4321.0])
    ref = brute_force_ft(k, n, b, T)
    np.testing.assert_allclose(profiles[name].ft_quadrature(k), ref, rtol=0, atol=1e-11)


def test_ft_rho2_contract(profiles):
    dev = profiles["devaucouleurs"]
    rho2 = np.linspace(0, 100, 24).reshape(2, 3, 4)
    out = dev.ft_rho2(rho2)
    assert out.shape == (2, 3, 4) and out.dtype == np.float64
    np.testing.assert_allclose(dev.ft(np.sqrt(rho2)), out, rtol=0, atol=1e-15)
    assert dev.ft_rho2(np.array([dev.rho_max ** 2 * 1.0001]))[0] == 0.0
    assert dev.ft_rho2(np.array([-1e-12]))[0] == 1.0  # round-off below 0
    assert np.all(np.diff(dev.rho2_nodes) > 0) and dev.rho2_nodes[-1] == dev.rho_max ** 2
    with pytest.raises(ValueError):
        dev.ft_nodes[0] = 0.5  # shared, memoised table


# ---------------------------------------------------------------------------
# 3. against GalSim

# GalSim's truncated Sersic k-values come from its own Hankel-transform table,
# spline-interpolated in ln k and built to kvalue_accuracy = 1e-8 (the
# documented accuracy of k values, in units of the flux). Interpolating the
# truncation's oscillating tail (amplitude ~ 0.02 k^-1.5, i.e. 6e-5 at k = 50)
# on a ln k grid costs it more than that at large k: measured 5e-9 for k < 10
# rising to 5e-7 at k ~ 50 (identical for maxk_threshold 1e-8 and 1e-6; the
# latter only sets the drawing maxk, and GalSim 2.8's intGKP fails with the
# former for the de Vaucouleurs profile). So: 1e-6 against our quadrature,
# 1e-6 + our table's 2e-6 against the table; both well below 1e-5.
GALSIM_TOL_QUADRATURE = 1e-6
GALSIM_TOL_TABLE = 3e-6


@pytest.fixture(scope="module")
def galsim_references():
    galsim = pytest.importorskip("galsim")
    tight = galsim.GSParams(kvalue_accuracy=1e-8, maxk_threshold=1e-8)
    tight_dev = galsim.GSParams(kvalue_accuracy=1e-8, maxk_threshold=1e-6)
    objs = {
        "exponential": galsim.Sersic(n=1, scale_radius=1, trunc=T, gsparams=tight),
        "devaucouleurs": galsim.DeVaucouleurs(half_light_radius=1, trunc=T, flux_untruncated=True,
                                              gsparams=tight_dev),
        "sersic2.5": galsim.Sersic(n=2.5, half_light_radius=1, trunc=T, flux_untruncated=True, gsparams=tight_dev),
        "sersic0.5": galsim.Sersic(n=0.5, half_light_radius=1, trunc=T, flux_untruncated=True, gsparams=tight_dev),
    }
    k = np.concatenate([np.linspace(0, 10, 41), np.linspace(10.3, 50, 80)])
    # With flux_untruncated=True GalSim's flux is the truncated profile's
    # share of unit untruncated flux (< 1); dividing by it normalises R(0) = 1.
    return k, {name: np.array([g.kValue(kk, 0.0).real for kk in k]) / g.flux for name, g in objs.items()}


@pytest.mark.parametrize("name", ["exponential", "devaucouleurs", "sersic2.5", "sersic0.5"])
def test_against_galsim(profiles, galsim_references, name):
    k, ref = galsim_references
    prof = profiles[name] if name in profiles else sersic(0.5)
    assert np.abs(prof.ft_quadrature(k) - ref[name]).max() < GALSIM_TOL_QUADRATURE
    assert np.abs(prof.ft(k) - ref[name]).max() < GALSIM_TOL_TABLE


# ---------------------------------------------------------------------------
# 4. untruncated limit


def test_exponential_untruncated_limit():
    # 2 pi int_0^inf e^-r J0(k r) r dr = 2 pi (1 + k^2)^-3/2 (the Laplace
    # transform of r J0(k r) at s = 1), and the flux is 2 pi, so
    # R(k) = (1 + k^2)^-1.5. Truncating at T = 40 drops int_T^inf e^-r r dr
    # = (1 + T) e^-T ~ 2e-16 of the flux, which bounds the change of R: the
    # limit is exact to double precision, and any difference is our error.
    prof = exponential_disk(40.0)
    k = np.concatenate([np.linspace(0, 20, 401), np.random.default_rng(3).uniform(0, 600, 400)])
    exact = (1 + k * k) ** -1.5
    assert np.abs(prof.ft_quadrature(k) - exact).max() < 1e-9
    assert np.abs(prof.ft(k) - exact).max() < 1e-6


# ---------------------------------------------------------------------------
# 5. half-light radius


def _hlr_by_root(prof):
    # Root of  int_0^r I s ds = (1/2) int_0^T I s ds, by quad + brentq: an
    # independent route to the module's incomplete-gamma inversion.
    def enclosed(r):
        # r = t^4 again tames the cusp.
        f = lambda t: prof.surface_brightness(t ** 4) * t ** 4 * 4 * t ** 3  # noqa: E731
        return 2 * np.pi * integrate.quad(f, 0.0, r ** 0.25, epsabs=1e-14, epsrel=1e-13, limit=200)[0]

    return optimize.brentq(lambda r: enclosed(r) - 0.5, 1e-3, T - 1e-9, xtol=1e-13)


def test_half_light_radius(profiles):
    # Untruncated exponential: 1 - (1 + r) e^-r = 1/2  ->  r = 1.678347.
    r_untrunc = optimize.brentq(lambda r: 1 - (1 + r) * np.exp(-r) - 0.5, 1, 2, xtol=1e-14)
    assert r_untrunc == pytest.approx(1.678347, abs=1e-6)
    exp = profiles["exponential"].half_light_radius()
    # Truncation removes the outer (1 + T) e^-T = 6.1% of the light, which
    # pulls the half-light radius in to ~1.58.
    assert 1.5 < exp < r_untrunc
    assert exp == pytest.approx(_hlr_by_root(profiles["exponential"]), abs=1e-9)
    # The de Vaucouleurs profile loses 13% of its light beyond 4.5 r_h: its
    # truncated half-light radius falls well below the nominal 1.
    dev = profiles["devaucouleurs"].half_light_radius()
    assert 0.7 < dev < 1.0
    assert dev == pytest.approx(_hlr_by_root(profiles["devaucouleurs"]), abs=1e-9)
    s25 = profiles["sersic2.5"].half_light_radius()
    assert dev < s25 < 1.0
    assert s25 == pytest.approx(_hlr_by_root(profiles["sersic2.5"]), abs=1e-9)


# ---------------------------------------------------------------------------
# factories


def test_factories_memoise(profiles):
    assert exponential_disk() is profiles["exponential"]
    assert exponential_disk(4.5) is exponential_disk(truncation=4.5)
    assert de_vaucouleurs() is de_vaucouleurs(4.5)
    assert sersic(2.5) is sersic(n=2.5, truncation=4.5)
    assert exponential_disk.cache_info().currsize >= 1
    # Unpickling hands back the process's shared instance, not a copy.
    assert pickle.loads(pickle.dumps(profiles["devaucouleurs"])) is profiles["devaucouleurs"]


def test_profile_metadata(profiles):
    assert [p.name for p in profiles.values()] == ["exponential", "devaucouleurs", "sersic2.5"]
    assert all(isinstance(p, RadialProfile) and p.truncation == 4.5 for p in profiles.values())
    assert profiles["devaucouleurs"].b == pytest.approx(7.66925, abs=1e-5)


@pytest.mark.parametrize("call", [lambda: exponential_disk(0.0), lambda: exponential_disk(np.inf),
                                  lambda: de_vaucouleurs("wide"), lambda: sersic(0.1), lambda: sersic(7.0)])
def test_invalid_arguments(call):
    with pytest.raises(ShearfitValueError):
        call()


@pytest.mark.parametrize("make", [lambda: exponential_disk(), lambda: de_vaucouleurs(), lambda: exponential_disk(3.0)])
def test_ft_rho2_is_np_interp_of_its_table(make):
    """ft_rho2 looks its nodes up by bucket (the compiled table_interp) where it can: np.interp's numbers, bit
    for bit, at random rho2 over 14 decades, negative ones, the nodes themselves and their neighbours, the
    ends, zero, infinities and NaN."""
    prof = make()
    xp, fp = prof.rho2_nodes, prof.ft_nodes
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.uniform(-1, 1, 500), 10 ** rng.uniform(-5, 9, 5000), xp, np.nextafter(xp, 0),
                        np.nextafter(xp, np.inf), xp[-3:] * 1.0000001, [0.0, -0.0, np.inf, -np.inf, np.nan]])
    rng.shuffle(x)
    assert np.array_equal(prof.ft_rho2(x), np.interp(x, xp, fp, right=0.0), equal_nan=True)
    y = x[:5 * (x.size // 5)].reshape(-1, 5)   # any shape
    assert np.array_equal(prof.ft_rho2(y), np.interp(y, xp, fp, right=0.0), equal_nan=True)
