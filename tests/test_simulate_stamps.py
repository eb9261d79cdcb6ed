"""Conventions of the GalSim stamp simulations (shearfit.simulate.stamps)."""

import galsim
import numpy as np
import pytest

import shearfit
from shearfit.simulate import (draw_psf_image, draw_stamp, galaxy_profile, kolmogorov_psf, make_observations,
                               moffat_psf, noise_for_snr, ring_set)

PIX = 0.187
J_SQUARE = PIX * np.eye(2)
J_SKEW = np.array([[0.15, 0.05], [-0.03, 0.2]])
J_ROT = PIX * np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
# Tight accuracy so that GalSim's own k-space truncation does not blur a 1e-6 pixel test.
TIGHT = galsim.GSParams(maxk_threshold=1e-9, folding_threshold=1e-9)


def centroid(img, x0=0, y0=0):
    ny, nx = img.shape
    y, x = np.mgrid[y0:y0 + ny, x0:x0 + nx]
    return (x * img).sum() / img.sum(), (y * img).sum() / img.sum()


def hsm_shape(prof, scale=0.02, n=480, guess=1.0):
    """Adaptive moments of a noise-free, pixel-free, well-sampled drawing."""
    im = prof.drawImage(nx=n, ny=n, scale=scale, method="no_pixel")
    res = galsim.hsm.FindAdaptiveMom(im, guess_sig=guess / scale)
    return res.moments_sigma * scale, res.observed_shape


# --------------------------------------------------------------------------- centre

@pytest.mark.parametrize("shape", [48, 49, (40, 51)])
@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.3, -0.41), (-0.5, 0.5)])
@pytest.mark.parametrize("J, tol", [(J_SQUARE, 1e-6), (J_ROT, 1e-5), (J_SKEW, 1e-5)])
def test_stamp_centre_convention(shape, offset, J, tol):
    # With a diagonal Jacobian GalSim's FFT drawing is exact to 1e-12 px here; through a
    # non-diagonal one its k-space evaluation (not separable, so a fast approximate exp) leaves
    # ~1e-6 px whatever the GSParams. A convention error would show at >= 1e-2 px.
    img = draw_stamp(galsim.Gaussian(sigma=0.25), galsim.Gaussian(sigma=0.15), J, offset, shape, gsparams=TIGHT)
    ny, nx = img.shape
    assert img.shape == ((shape, shape) if np.ndim(shape) == 0 else shape)
    xc, yc = centroid(img)
    assert xc == pytest.approx(nx // 2 + offset[0], abs=tol)
    assert yc == pytest.approx(ny // 2 + offset[1], abs=tol)


def test_stamp_is_image_y_x():
    # A profile elongated along world u (= +x for a square grid) spreads along axis 1 of the array.
    img = draw_stamp(galsim.Gaussian(sigma=0.3).shear(g1=0.5), galsim.Gaussian(sigma=0.1), J_SQUARE, stamp_size=48)
    assert img[24, :].sum() > img[:, 24].sum()


# --------------------------------------------------------------------------- profiles

@pytest.mark.parametrize("B, is_bulge", [(0.0, False), (0.35, False), (1.0, True)])
def test_flux_of_large_stamp(B, is_bulge):
    prof = galaxy_profile(0.3, B, 0.2, -0.4, flux=123.4, g1=0.05, g2=0.02, is_bulge=is_bulge)
    assert prof.flux == pytest.approx(123.4, rel=1e-12)
    img = draw_stamp(prof, galsim.Gaussian(sigma=0.2), J_SQUARE, (0.2, -0.1), 128)
    assert img.sum() == pytest.approx(123.4, rel=1e-3)


def test_semi_major_axis_fixed_adaptive_moments():
    # An elliptical profile f(|A^-1 x|) has adaptive moments A M0 A^T, so the major-axis sigma
    # is sigma_hsm * sqrt((1+g)/(1-g)) and must equal the round profile's sigma.
    s0, shape0 = hsm_shape(galaxy_profile(1.0, 0.0, 0.0, 0.0))
    e = 0.6
    s6, shape6 = hsm_shape(galaxy_profile(1.0, 0.0, e * np.cos(0.7), e * np.sin(0.7)))
    g = shape6.g
    assert abs(shape0.g) < 1e-6
    assert g == pytest.approx(e, abs=1e-4)
    assert shape6.beta.rad == pytest.approx(0.35, abs=1e-4)
    assert s6 * np.sqrt((1 + g) / (1 - g)) == pytest.approx(s0, rel=1e-3)


@pytest.mark.parametrize("B, is_bulge", [(0.0, False), (0.4, False), (1.0, True)])
def test_semi_major_axis_fixed_profile_values(B, is_bulge):
    # Along the major axis the elliptical profile is the round one; along the minor axis it is
    # the round one compressed by q. Checked on the surface brightness itself, for every type.
    e, theta = 0.6, 0.35
    q = (1 - e) / (1 + e)
    round_ = galaxy_profile(0.8, B, 0.0, 0.0, is_bulge=is_bulge)
    ell = galaxy_profile(0.8, B, e * np.cos(2 * theta), e * np.sin(2 * theta), is_bulge=is_bulge)
    major = np.array([np.cos(theta), np.sin(theta)])
    minor = np.array([-np.sin(theta), np.cos(theta)])
    for R in (0.1, 0.8, 2.0, 3.5):
        ref = round_.xValue(R, 0.0) / round_.xValue(0.0, 0.0)
        assert ell.xValue(*(R * major)) / ell.xValue(0.0, 0.0) == pytest.approx(ref, rel=1e-9)
        assert ell.xValue(*(q * R * minor)) / ell.xValue(0.0, 0.0) == pytest.approx(ref, rel=1e-9)
    # truncated at 4.5 scalelengths along the major axis
    assert ell.xValue(*(4.4 * 0.8 * major)) > 0
    assert ell.xValue(*(4.6 * 0.8 * major)) == 0
    # the transformation's singular values are the axes of a unit circle: 1 and q
    assert np.linalg.svd(ell.jac)[1] == pytest.approx([1.0, q], rel=1e-12)


def test_profile_conventions_of_paper():
    r = 0.5
    bulge = galaxy_profile(r, 1.0, 0.0, 0.0, is_bulge=True)
    # the paper's r_h is that of the untruncated exp(-7.67 (R/r_h)^(1/4))
    assert np.log(bulge.xValue(r, 0) / bulge.xValue(0, 0)) == pytest.approx(-7.66925, abs=1e-4)
    disk = galaxy_profile(r, 0.0, 0.0, 0.0)
    assert np.log(disk.xValue(r, 0) / disk.xValue(0, 0)) == pytest.approx(-1.0, rel=1e-9)
    # bulge and disk share the half-light / scale radius r, flux split by B
    comp = galaxy_profile(r, 0.3, 0.0, 0.0, flux=2.0)
    assert comp.xValue(0.2, 0.1) == pytest.approx(2.0 * (0.3 * bulge.xValue(0.2, 0.1) + 0.7 * disk.xValue(0.2, 0.1)),
                                                  rel=1e-9)
    # is_bulge ignores bulge_fraction
    assert galaxy_profile(r, 0.2, 0.0, 0.0, is_bulge=True).xValue(0.3, 0) == pytest.approx(bulge.xValue(0.3, 0))


def test_shear_composition_eq1():
    es, g = complex(0.3, 0.2), complex(0.05, -0.1)
    expected = (es + g) / (1 + g.conjugate() * es)  # paper eq. (1)
    # GalSim's shear addition is the same composition
    s = galsim.Shear(g1=g.real, g2=g.imag) + galsim.Shear(g1=es.real, g2=es.imag)
    assert s.g1 == pytest.approx(expected.real, abs=1e-12)
    assert s.g2 == pytest.approx(expected.imag, abs=1e-12)
    prof = galaxy_profile(1.0, 0.0, es.real, es.imag, g1=g.real, g2=g.imag)
    # the shape of the transformed unit circle: polar decomposition of the jacobian
    M = prof.jac @ prof.jac.T
    w, V = np.linalg.eigh(M)
    a, b = np.sqrt(w[1]), np.sqrt(w[0])
    phi = np.arctan2(V[1, 1], V[0, 1])
    assert (a - b) / (a + b) * np.exp(2j * phi) == pytest.approx(expected, abs=1e-12)
    # and in the pixels, measured by adaptive moments
    _, shape = hsm_shape(prof)
    assert complex(shape.g1, shape.g2) == pytest.approx(expected, abs=2e-4)


def test_bad_profile_arguments():
    with pytest.raises(ValueError):
        galaxy_profile(0.3, 0.0, 0.8, 0.7)
    with pytest.raises(ValueError):
        galaxy_profile(-0.3, 0.0, 0.1, 0.1)
    with pytest.raises(ValueError):
        galaxy_profile(0.3, 1.5, 0.1, 0.1)


# --------------------------------------------------------------------------- PSF images

@pytest.mark.parametrize("J", [J_SQUARE, J_SKEW])
def test_psf_image_native_and_oversampled(J):
    psf = moffat_psf(0.6, 3.0, 0.05, -0.08)
    native = draw_psf_image(psf, J)
    assert native.shape == (48, 48)
    assert native.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.unravel_index(native.argmax(), native.shape) == (24, 24)
    # centroid over the window symmetric about n//2 (an even array has an unpaired row 0)
    xc, yc = centroid(native[1:, 1:], 1, 1)
    assert (xc, yc) == pytest.approx((24, 24), abs=1e-9)
    for k in (2, 3):
        over = draw_psf_image(psf, J, oversampling=k)
        n = 48 * k
        assert over.shape == (n, n)
        assert over.sum() == pytest.approx(1.0, abs=1e-12)
        xc, yc = centroid(over[1:, 1:], 1, 1)
        assert (xc, yc) == pytest.approx((n // 2, n // 2), abs=1e-9)
        # same pixel-convolved PSF: every k-th sample lands on a native pixel centre
        assert np.abs(over[::k, ::k] * k * k - native).max() < 2e-3 * native.max()


def test_psf_image_ellipticity_follows_world_frame():
    # With a 90-degree rotated pixel grid, a PSF elongated along u lies along y.
    psf = moffat_psf(0.7, 3.0, 0.1, 0.0)
    rot = PIX * np.array([[0.0, -1.0], [1.0, 0.0]])
    img = draw_psf_image(psf, rot, size=32)
    assert img[:, 16].sum() > img[16, :].sum()


# --------------------------------------------------------------------------- noise and observations

def test_noise_for_snr():
    rng = np.random.default_rng(3)
    stamps = [rng.normal(size=(20, 20)) for _ in range(5)]
    sigma = noise_for_snr(stamps, 25.0)
    assert np.sqrt(sum((m ** 2).sum() for m in stamps)) / sigma == pytest.approx(25.0, rel=1e-12)
    assert noise_for_snr(stamps[0], 10.0) == pytest.approx(np.sqrt((stamps[0] ** 2).sum()) / 10.0)
    with pytest.raises(ValueError):
        noise_for_snr(stamps, 0.0)


def test_make_observations():
    rng = np.random.default_rng(11)
    prof = galaxy_profile(0.3, 0.1, 0.2, 0.1, flux=1000.0)
    psfs = [moffat_psf(0.6, 3.0), moffat_psf(0.7, 2.5, 0.05, 0.0)]
    Js = [J_SQUARE, J_SKEW]
    offsets = [(0.1, -0.2), (0.4, 0.3)]
    obs = make_observations(prof, psfs, Js, offsets, [2.0, 3.0], rng, psf_oversampling=2, flux_scales=[1.0, 1.5])
    assert len(obs) == 2 and all(isinstance(o, shearfit.Observation) for o in obs)
    for o, J, off, sig, fs, psf in zip(obs, Js, offsets, [2.0, 3.0], [1.0, 1.5], psfs):
        assert o.image.shape == (48, 48) and o.psf.shape == (96, 96) and o.psf_oversampling == 2
        assert np.all(o.weight == 1.0 / sig ** 2)
        assert np.allclose(o.jacobian, J) and np.allclose(o.offset, off) and o.flux_scale == fs
        model = draw_stamp(prof * fs, psf, J, off)
        resid = o.image - model
        assert resid.std() == pytest.approx(sig, rel=0.05)
        assert abs(resid.mean()) < 4 * sig / 48


# --------------------------------------------------------------------------- ring sets

def test_ring_set_structure_and_noise_cancellation():
    kw = dict(n_rotations=2, n_exposures=3, snr_range=(40, 50))
    plus = ring_set(2, (0.03, -0.02), np.random.default_rng(7), **kw)
    minus = ring_set(2, (-0.03, 0.02), np.random.default_rng(7), **kw)
    assert len(plus) == 4
    for (op, tp), (om, tm) in zip(plus, minus):
        assert len(op) == 3
        for key in ("scalelength", "bulge_fraction", "is_bulge", "mag", "snr", "sigma", "e1_int", "e2_int"):
            assert tp[key] == tm[key]
        assert (tp["g1"], tp["g2"]) == (0.03, -0.02) and (tm["g1"], tm["g2"]) == (-0.03, 0.02)
        assert tp["snr_true"] == pytest.approx(tp["snr"], rel=0.05)
        half = 24 * PIX
        assert 4.5 * tp["scalelength"] + 2 * tp["psf_fwhm"].max() <= half
        # identical noise: the image difference is the noise-free difference
        for k in range(3):
            def model(t, i=k):
                prof = galaxy_profile(t["scalelength"], t["bulge_fraction"], t["e1_int"], t["e2_int"],
                                      flux=t["flux"], g1=t["g1"], g2=t["g2"], is_bulge=t["is_bulge"])
                psf = moffat_psf(t["psf_fwhm"][i], t["psf_beta"][i], t["psf_e1"][i], t["psf_e2"][i])
                return draw_stamp(prof, psf, J_SQUARE, t["offsets"][i])
            np.testing.assert_allclose(op[k].image - om[k].image, model(tp) - model(tm), atol=1e-9 * tp["flux"])
            noise = op[k].image - model(tp)
            assert noise.std() == pytest.approx(tp["sigma"], rel=0.1)
    # the ring: rotation j turns the intrinsic ellipticity by 2 pi j / n in the e-plane
    e0 = complex(plus[0][1]["e1_int"], plus[0][1]["e2_int"])
    e1 = complex(plus[1][1]["e1_int"], plus[1][1]["e2_int"])
    assert e1 == pytest.approx(-e0, abs=1e-12)


def test_ring_set_noise_seed_and_rotated_grids():
    kw = dict(n_rotations=1, n_exposures=2, rotate_exposures=True, psf_oversampling=2)
    a = ring_set(1, (0.02, 0.0), np.random.default_rng(1), noise_seed=5, **kw)
    b = ring_set(1, (0.02, 0.0), np.random.default_rng(1), noise_seed=5, **kw)
    c = ring_set(1, (0.02, 0.0), np.random.default_rng(1), noise_seed=6, **kw)
    assert np.array_equal(a[0][0][0].image, b[0][0][0].image)
    assert not np.array_equal(a[0][0][0].image, c[0][0][0].image)
    J = a[0][0][1].jacobian
    assert np.sqrt(abs(np.linalg.det(J))) == pytest.approx(PIX)
    assert np.allclose(J @ J.T, PIX ** 2 * np.eye(2))
    assert a[0][0][1].psf.shape == (96, 96)


@pytest.mark.parametrize("J", [J_SQUARE, J_ROT])
def test_star_stamp_matches_psf_image(J):
    # A point source drawn as a stamp is the Observation's PSF image times its flux: the two
    # drawings share centre, pixel response and orientation.
    psf = moffat_psf(0.65, 3.5, -0.06, 0.04)
    star = draw_stamp(galsim.DeltaFunction(flux=50.0), psf, J)
    native = draw_psf_image(psf, J)
    assert np.abs(star / star.sum() - native).max() < 1e-3 * native.max()


def test_sersic_galaxy_outside_the_models():
    """sersic_n: one Sersic profile with the exponential's half-light radius for that scalelength."""
    r = 0.4
    p = galaxy_profile(r, 0.3, 0.0, 0.0, flux=7.0, sersic_n=2.5, truncation=20.0)
    ref = galsim.Sersic(n=2.5, half_light_radius=galsim.Exponential(scale_radius=r).half_light_radius,
                        trunc=20 * r, flux_untruncated=True)
    assert p.flux == pytest.approx(7.0)
    im = p.drawImage(nx=64, ny=64, scale=0.05, method="no_pixel").array
    im_ref = ref.withFlux(7.0).drawImage(nx=64, ny=64, scale=0.05, method="no_pixel").array
    assert np.allclose(im, im_ref, atol=1e-6 * im_ref.max())


def test_ring_set_antithetic_twin_negates_only_the_noise():
    """noise_sign=-1: the same galaxies, PSFs and dithers, and noise exactly minus the +1 run's (with the
    noise drawn from the main generator or from noise_seed): the twins average to the noise-free stamps."""
    for kw in ({}, {"noise_seed": 5}):
        a = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, **kw)
        b = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, noise_sign=-1, **kw)
        for (oa, ta), (ob, tb) in zip(a, b):
            assert ta["e1_int"] == tb["e1_int"] and ta["scalelength"] == tb["scalelength"]
            assert ta["sigma"] == tb["sigma"]
            for x, y in zip(oa, ob):
                assert np.std(x.image - y.image) > ta["sigma"]     # the noise differs ...
    clean = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, noise_seed=5,
                     add_noise=False)
    for (oa, _), (ob, _), (oc, _) in zip(a, b, clean):
        for x, y, z in zip(oa, ob, oc):
            assert np.max(np.abs(x.image + y.image - 2 * z.image)) < 1e-10 * np.max(z.image)   # ... by its sign


def test_ring_set_antithetic_in_one_call_is_the_two_calls():
    """antithetic=True returns each orientation followed by its twin: the members of a call with noise_sign +1
    and the twins of one with -1 (a generator in the same state), every pixel and truth value the same, for
    noise from the main generator and from noise_seed; the truth says which sign each has."""
    for kw in ({}, {"noise_seed": 5}):
        both = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, antithetic=True, **kw)
        a = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, **kw)
        b = ring_set(3, (0.02, 0.0), np.random.default_rng(3), n_rotations=2, n_exposures=2, noise_sign=-1, **kw)
        assert len(both) == 2 * len(a)
        for (o1, t1), (o2, t2), (oa, ta), (ob, tb) in zip(both[0::2], both[1::2], a, b):
            assert (t1["noise_sign"], t2["noise_sign"], ta["noise_sign"], tb["noise_sign"]) == (1, -1, 1, -1)
            for t, ref in ((t1, ta), (t2, tb)):
                assert t.keys() == ref.keys()
                assert all(np.array_equal(t[k], ref[k]) for k in t if k != "fields") and t["fields"] == ref["fields"]
            for x, y, u, v in zip(o1, o2, oa, ob):
                assert np.array_equal(x.image, u.image) and np.array_equal(y.image, v.image)
                assert np.array_equal(x.psf, u.psf) and np.array_equal(y.weight, v.weight)
                assert not np.array_equal(x.image, y.image)


def test_ring_set_jacobian_jitter():
    """jacobian_jitter: each exposure's Jacobian is J (1 + A), A of the given rms; the +g and -g runs see the
    same ones, and the truth records them."""
    kw = dict(n_rotations=1, n_exposures=6, jacobian_jitter=1e-3, noise_seed=5)
    a = ring_set(2, (0.02, 0.0), np.random.default_rng(4), **kw)
    b = ring_set(2, (-0.02, 0.0), np.random.default_rng(4), **kw)
    for (oa, ta), (ob, _) in zip(a, b):
        Js = np.array([o.jacobian for o in oa])
        assert np.array_equal(Js, np.array([o.jacobian for o in ob]))
        assert np.array_equal(Js, ta["jacobians"])
        dev = Js / PIX - np.eye(2)
        assert 2e-4 < np.std(dev) < 3e-3
    plain = ring_set(2, (0.02, 0.0), np.random.default_rng(4), n_rotations=1, n_exposures=6, noise_seed=5)
    assert all(np.array_equal(o.jacobian, PIX * np.eye(2)) for o in plain[0][0])


def test_ring_set_kolmogorov_psfs_change_only_the_psf():
    """psf_family="kolmogorov": each exposure's PSF image is GalSim's Kolmogorov of the drawn FWHM and
    ellipticity, not the Moffat's, and every other draw is the Moffat run's; an unknown family is refused."""
    kw = dict(n_rotations=1, n_exposures=3, noise_seed=5)
    mo = ring_set(1, (0.02, 0.0), np.random.default_rng(4), **kw)
    ko = ring_set(1, (0.02, 0.0), np.random.default_rng(4), psf_family="kolmogorov", **kw)
    (om, tm), (ok, tk) = mo[0], ko[0]
    for key in ("scalelength", "e1_int", "e2_int", "psf_fwhm", "psf_e1", "psf_e2", "offsets"):
        assert np.array_equal(np.asarray(tm[key]), np.asarray(tk[key])), key
    for i, o in enumerate(ok):
        want = draw_psf_image(kolmogorov_psf(tk["psf_fwhm"][i], tk["psf_e1"][i], tk["psf_e2"][i]), o.jacobian)
        np.testing.assert_allclose(o.psf, want, atol=1e-12)
        assert not np.allclose(o.psf, om[i].psf, atol=1e-4)
    with pytest.raises(shearfit.ShearfitValueError, match="psf_family"):
        ring_set(1, (0.02, 0.0), np.random.default_rng(4), psf_family="airy", **kw)


@pytest.mark.parametrize("family", ["sersic", "bulge_disk", "knots"])
def test_galaxies_outside_the_model_family(family):
    """shearfit.simulate.outside: each family's profile has the flux asked for, its ring members are the galaxy
    turned as a whole (their mean ellipticity vanishes without shear, whatever the profile), and ring_set
    draws them through its ``profile`` hook."""
    from shearfit.simulate.outside import FAMILIES, outside_population, outside_profile

    rng = np.random.default_rng(3)
    pop = outside_population(np.full(40, 22.0), rng, families=(family,))
    assert np.all(pop["family"] == FAMILIES.index(family))
    assert pop["hlr"].min() >= 0.1 and pop["hlr"].max() <= 2.0
    k = int(np.argmax(np.hypot(pop["e1"], pop["e2"]) > 0.2))   # a clearly elliptical one
    fields = {name: v[k].item() for name, v in pop.items()}
    fields["hlr"] = 0.5
    prof = outside_profile(fields, 0.0, 0.0, 0.0, flux=3.0)
    assert prof.flux == pytest.approx(3.0)
    # (through a small round Gaussian: the knots are points)
    shapes = [hsm_shape(galsim.Convolve(outside_profile(fields, np.pi * j / 4, 0.0, 0.0, 1.0), galsim.Gaussian(sigma=0.05)),
                        guess=0.5)[1] for j in range(4)]
    e = np.array([[s.e1, s.e2] for s in shapes])
    assert np.hypot(*e[0]) > 0.05
    assert np.abs(e.mean(axis=0)).max() < 1e-3 * np.hypot(*e[0]) + 1e-5
    # a turn by pi / 2 turns e by pi: the turned galaxy's e is minus the first's
    assert e[2] == pytest.approx(-e[0], abs=2e-3)
    rings = ring_set(1, (0.0, 0.0), np.random.default_rng(4), n_rotations=2, n_exposures=1, stamp_size=64,
                     population=lambda m, r, c: outside_population(m, r, c, families=(family,)),
                     profile=outside_profile, add_noise=False)
    (o0, t0), (o1, t1) = rings
    assert t0["fields"]["family"] == FAMILIES.index(family)
    ref = draw_stamp(outside_profile(t1["fields"], np.pi / 2, 0.0, 0.0, t1["flux"]),
                     moffat_psf(t1["psf_fwhm"][0], t1["psf_beta"][0], t1["psf_e1"][0], t1["psf_e2"][0]),
                     J_SQUARE, t1["offsets"][0], 64)
    np.testing.assert_allclose(o1[0].image, ref, atol=1e-9 * t1["flux"])


def test_ring_set_fixed_noise_sigma_keeps_the_magnitudes_flux():
    """noise_sigma: every galaxy has that pixel sigma and its magnitude's flux (as on a field of one depth),
    and the truth's snr is the one the sigma gives the unsheared galaxy; the same draws otherwise."""
    a = ring_set(4, (0.02, 0.0), np.random.default_rng(6), n_rotations=2, n_exposures=3, noise_sigma=4.0,
                 mag_range=(23.0, 24.5), add_noise=False)
    b = ring_set(4, (0.02, 0.0), np.random.default_rng(6), n_rotations=2, n_exposures=3, snr_range=(10, 20),
                 mag_range=(23.0, 24.5), add_noise=False)
    for (oa, ta), (ob, tb) in zip(a, b):
        assert ta["sigma"] == 4.0 and ta["flux"] == pytest.approx(10 ** (-0.4 * (ta["mag"] - 30.0)))
        assert ta["scalelength"] == tb["scalelength"] and ta["mag"] == tb["mag"]
        assert all(np.allclose(x.image, y.image) for x, y in zip(oa, ob))     # noise-free: the same stamps
        assert all(np.allclose(x.weight, 1 / 16.0) for x in oa)
        if ta["rotation"] == 0:
            assert ta["snr"] == pytest.approx(tb["snr"] * tb["sigma"] / 4.0, rel=0.02)


def test_ring_set_population_may_set_the_magnitude():
    """A population that returns a ``mag`` (a simulated field's galaxies) sets the galaxy's magnitude and
    flux, whatever was drawn from mag_range."""
    from shearfit.engine.priors import sample_population

    def fixed(mags, rng, cfg):
        pop = sample_population(mags, rng, cfg)
        pop["mag"] = 22.25
        return pop

    out = ring_set(2, (0.02, 0.0), np.random.default_rng(2), n_rotations=1, n_exposures=2, population=fixed,
                   mag_range=(23.0, 24.0), add_noise=False)
    for _, t in out:
        assert t["mag"] == 22.25 and t["flux"] == pytest.approx(10 ** (-0.4 * (22.25 - 30.0)))


# --------------------------------------------------------------------------- drawing with the PSF's transform kept

@pytest.mark.parametrize("shape", [48, (40, 51)])
def test_draw_stamp_psf_cache_is_galsims_drawing(shape):
    """draw_stamp with psf_cache (GalSim's FFT drawing in parts, the PSF's transform kept per grid) gives
    drawImage's stamp to rounding, for galaxies in and outside the model family, elliptical PSFs, rotated
    and skewed pixels and sub-pixel offsets; the PSF is transformed once per PSF, Jacobian and grid."""
    from shearfit.simulate.outside import outside_population, outside_profile

    pop = outside_population(np.full(6, 23.0), np.random.default_rng(5))
    profiles = [outside_profile({k: v[i] for k, v in pop.items()}, 0.3 * i, 0.02, -0.01, 500.0) for i in range(6)]
    profiles.append(galaxy_profile(0.3, 0.4, 0.2, -0.1, flux=500.0))
    cache = {}
    for J in (J_ROT, J_SKEW):
        for psf in (moffat_psf(0.7, 2.5, 0.05, -0.03), moffat_psf(0.55, 4.0)):
            for i, prof in enumerate(profiles):
                off = (0.1 * i - 0.3, 0.45 - 0.07 * i)
                ref = draw_stamp(prof, psf, J, off, shape)
                got = draw_stamp(prof, psf, J, off, shape, psf_cache=cache)
                np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * ref.max())
    # far fewer PSF transforms than stamps: the galaxies of one PSF and Jacobian share GalSim's grid
    assert 4 <= len(cache) < 2 * 2 * len(profiles) / 2
    # a changed PSF is not taken for the kept one
    other = draw_stamp(profiles[0], moffat_psf(0.7, 2.5, 0.05, 0.03), J_ROT, (0.0, 0.0), shape, psf_cache=cache)
    np.testing.assert_allclose(other, draw_stamp(profiles[0], moffat_psf(0.7, 2.5, 0.05, 0.03), J_ROT, (0.0, 0.0),
                                                 shape), rtol=0, atol=1e-13 * other.max())


def test_ring_set_draw_cache_shared_by_the_signs():
    """A draw_cache shared by a +g and a -g call draws the same stamps and PSF images as calls without it,
    and leaves the unsheared stamps (which set the noise) drawn once for both."""
    from shearfit.simulate.outside import outside_population, outside_profile

    kw = dict(n_rotations=2, n_exposures=2, rotate_exposures=True, population=outside_population,
              profile=outside_profile, antithetic=True)
    cache = {}
    for g in ((0.03, -0.02), (-0.03, 0.02)):
        ref = ring_set(2, g, np.random.default_rng(9), **kw)
        got = ring_set(2, g, np.random.default_rng(9), draw_cache=cache, **kw)
        assert len(got) == len(ref)
        for (o1, t1), (o2, t2) in zip(got, ref):
            assert t1["sigma"] == pytest.approx(t2["sigma"], rel=1e-13)
            for x, y in zip(o1, o2):
                np.testing.assert_allclose(x.image, y.image, rtol=0, atol=1e-12 * np.abs(y.image).max())
                assert np.array_equal(x.psf, y.psf)
    kinds = [k[0] for k in cache]
    assert kinds.count("stamps") == 2 and kinds.count("psf_image") == 4


def test_negated_generator_copies_and_pickles():
    """A NegatedNormal (the antithetic twin's generator) can be deep-copied and pickled, as a numpy Generator can:
    the copy draws what the original would, negated where the original negates; its attribute lookup used to
    recurse without end on a copy, whose ``rng`` is not yet set when the copy is made."""
    import copy
    import pickle

    from shearfit.simulate.stamps import NegatedNormal, _RecordedNormal

    a = NegatedNormal(np.random.default_rng(4))
    for b in (copy.deepcopy(a), pickle.loads(pickle.dumps(a))):
        assert np.array_equal(b.normal(size=5), -np.random.default_rng(4).normal(size=5))
    r = copy.deepcopy(_RecordedNormal(np.random.default_rng(4)))
    assert np.array_equal(r.normal(size=3), np.random.default_rng(4).normal(size=3)) and len(r.drawn) == 1
