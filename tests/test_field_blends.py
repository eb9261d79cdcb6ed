"""Neighbour masking, bad pixels, blends and centroids on the smoothed co-add (paper sec. 3.6).

Tier 1: the smoothing kernel, the co-add's noise computed from the weights,
and the deblender on hand-made images. Tier 2: GalSim draws galaxies (Gaussian,
exponential and de Vaucouleurs profiles convolved with a Moffat PSF, Gaussian
pixel noise) and :func:`analyse_stamps` classifies them. Tier 3 (slow): the
false-blend rate over the paper's galaxy population and the detection of close
pairs.
"""

import math

import numpy as np
import pytest
from scipy import ndimage

galsim = pytest.importorskip("galsim")

from shearfit.errors import (FITCLASS_BLENDED, FITCLASS_CENTROID, FITCLASS_GALAXY,  # noqa: E402
                             ShearfitValueError)
from shearfit.pipeline.blends import (_deblend, _significant_maxima, analyse_stamps, smooth_coadd,  # noqa: E402
                                   smoothing_kernel)

PIX = 0.187  # arcsec per pixel (MegaCam)
N = 48  # stamp side (paper sec. 3.6)
NEXP = 7
PSF_FWHM = 0.7  # arcsec: 3.74 pixels


# --- helpers ------------------------------------------------------------------------------

def moffat(fwhm=PSF_FWHM):
    return galsim.Moffat(beta=3.0, fwhm=fwhm)


def render(objects, offsets, psf):
    """Noise-free stamps: each (profile, (px, py)) drawn at stamp centre + exposure offset + (px, py)."""
    out = []
    for dx, dy in offsets:
        img = np.zeros((N, N))
        for prof, (px, py) in objects:
            # use_true_center=False puts offset (0, 0) at index (N // 2, N // 2), the stamps' convention
            im = galsim.Convolve(prof, psf).drawImage(nx=N, ny=N, scale=PIX, use_true_center=False,
                                                      offset=(dx + px, dy + py), dtype=np.float64)
            img += im.array
        out.append(img)
    return out


class Sim:
    """Noise-free exposures of some objects; ``observe`` adds noise for a target S/N."""

    def __init__(self, objects, rng, n_exp=NEXP, psf_fwhm=PSF_FWHM):
        self.offsets = rng.uniform(-0.5, 0.5, (n_exp, 2))
        self.psf_fwhm_pixels = psf_fwhm / PIX
        psf = moffat(psf_fwhm)
        self.clean = render(objects, self.offsets, psf)
        # the S/N is the first object's, summed over exposures: sqrt(sum m^2) / sigma
        target = render(objects[:1], self.offsets, psf)
        self.power = math.sqrt(sum(float(np.sum(m * m)) for m in target))

    def observe(self, snr, rng):
        sigma = self.power / snr
        stamps = [c + rng.normal(0.0, sigma, c.shape) for c in self.clean]
        weights = [np.full(c.shape, sigma ** -2) for c in self.clean]
        return stamps, weights, self.offsets

    def analyse(self, snr, rng, **kw):
        stamps, weights, offsets = self.observe(snr, rng)
        return analyse_stamps(stamps, weights, offsets, self.psf_fwhm_pixels, **kw)


def exp_gal(hlr, g1=0.0, g2=0.0, flux=1.0):
    return galsim.Exponential(half_light_radius=hlr, flux=flux).shear(g1=g1, g2=g2)


def pixel_of(offsets, pos):
    """(row, column) of the co-add pixel nearest to ``pos`` (x, y) relative to the nominal position."""
    return (N // 2 + int(round(offsets[:, 1].mean() + pos[1])), N // 2 + int(round(offsets[:, 0].mean() + pos[0])))


def random_direction(rng):
    a = rng.uniform(0.0, 2.0 * np.pi)
    return np.array([math.cos(a), math.sin(a)])


# --- tier 1: kernel, noise, deblender ----------------------------------------------------

@pytest.mark.parametrize("fwhm", [2.5, 3.74, 6.0])
def test_kernel_unit_sum_and_width(fwhm):
    k = smoothing_kernel(fwhm)
    assert k.size % 2 == 1
    assert k.sum() == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(k, k[::-1], rtol=0, atol=1e-16)
    x = np.arange(k.size) - k.size // 2
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    # sampled at least once per sigma and cut at 4 sigma, a Gaussian keeps its width to 1e-3
    assert np.sqrt(np.sum(k * x * x)) == pytest.approx(sigma, rel=1e-3)


def test_kernel_rejects_bad_fwhm():
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ShearfitValueError):
            smoothing_kernel(bad)


def test_smoothed_noise_is_computed_from_weights():
    # Uniform weight w on n exposures: co-add variance 1 / (n w), and away from the edges
    # the smoothed variance is that times sum K^2 = (sum k^2)^2 for the separable kernel.
    n, w, fwhm = 5, 4.0, 3.74
    stamps = [np.zeros((N, N))] * n
    sc = smooth_coadd(stamps, [np.full((N, N), w)] * n, fwhm)
    k = smoothing_kernel(fwhm)
    expect = math.sqrt(1.0 / (n * w)) * np.sum(k * k)
    r = k.size // 2
    np.testing.assert_allclose(sc.noise[r:-r, r:-r], expect, rtol=1e-12)
    # at the corner half the kernel falls off the stamp, onto noiseless background
    assert sc.noise[0, 0] < expect
    # and the discrete sum K^2 is the continuous integral of a unit Gaussian squared,
    # 1 / (4 pi sigma^2), for a kernel sampled finer than its sigma
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    assert np.sum(k * k) ** 2 == pytest.approx(1.0 / (4 * math.pi * sigma ** 2), rel=1e-3)


def test_coadd_is_weighted_mean_and_skips_bad_pixels():
    rng = np.random.default_rng(0)
    stamps = [rng.normal(size=(N, N)) for _ in range(3)]
    weights = [np.full((N, N), v) for v in (1.0, 2.0, 3.0)]
    weights[1][10, 12] = 0.0
    stamps[1][10, 12] = np.nan  # a bad pixel's value must not leak in
    sc = smooth_coadd(stamps, weights, 3.0)
    expect = (stamps[0] + 2 * stamps[1] + 3 * stamps[2]) / 6.0
    np.testing.assert_allclose(sc.coadd[20, 20], expect[20, 20], rtol=1e-12)
    assert sc.coadd[10, 12] == pytest.approx((stamps[0][10, 12] + 3 * stamps[2][10, 12]) / 4.0, rel=1e-12)
    assert np.all(np.isfinite(sc.snr))


def test_smoothed_noise_matches_monte_carlo():
    # Non-uniform weights (a gradient, a dead patch in one exposure): the S/N map of pure
    # noise must have unit variance wherever the formula is right. Sampling pixels 14 apart
    # (the kernel's 4-sigma half-width is 7) keeps them independent: 11 x 11 per image,
    # 8 images, 968 samples, so the sample variance has a relative error of
    # sqrt(2 / 968) = 0.045; the tolerance is 4 of those.
    rng = np.random.default_rng(1)
    size = 160
    yy, xx = np.mgrid[:size, :size]
    wmaps = [1.0 + xx / size, 0.5 + yy / size, np.full((size, size), 2.0)]
    wmaps[2][40:90, 60:120] = 0.0
    vals = []
    for _ in range(8):
        stamps = [rng.normal(size=(size, size)) / np.sqrt(np.maximum(w, 1e-300)) for w in wmaps]
        sc = smooth_coadd(stamps, wmaps, 3.74)
        vals.append(sc.snr[7:-7:14, 7:-7:14].ravel())
    var = np.var(np.concatenate(vals))
    assert var == pytest.approx(1.0, abs=4 * math.sqrt(2 / 968))


def _ridge(values):
    """A one-row region holding ``values`` inside a frame of zeros."""
    v = np.zeros((3, len(values) + 2))
    v[1, 1:-1] = values
    return v, v > 0


def test_significant_maxima_prominence_and_ties():
    # two equal peaks (10) joined at 8.5: a dip of 1.5 < 3 -> one maximum counts
    v, region = _ridge([3, 5, 10, 8.5, 10, 5, 3])
    assert _significant_maxima(np.where(region, v, -np.inf), region, 2.0, 3.0).sum() == 1
    # 10 and 9.5 joined at 6: the lower one stands 3.5 above its col -> both count
    v, region = _ridge([3, 5, 10, 6, 9.5, 5, 3])
    assert _significant_maxima(np.where(region, v, -np.inf), region, 2.0, 3.0).sum() == 2
    # and with a larger contrast demanded it no longer does
    assert _significant_maxima(np.where(region, v, -np.inf), region, 2.0, 4.0).sum() == 1


def _two_blobs(sep, amp2, shape=(31, 41), amp1=40.0, sigma=2.5):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    c = (shape[0] // 2, 12)
    img = amp1 * np.exp(-((xx - c[1]) ** 2 + (yy - c[0]) ** 2) / (2 * sigma ** 2))
    img += amp2 * np.exp(-((xx - c[1] - sep) ** 2 + (yy - c[0]) ** 2) / (2 * sigma ** 2))
    return img


def test_deblend_splits_two_resolved_blobs_and_not_one():
    img = _two_blobs(12, 30.0)
    region = img >= 2.0
    assert ndimage.label(region, structure=np.ones((3, 3)))[1] == 1  # one isophote, two peaks
    for spacing in ("linear", "log"):
        lab, n = _deblend(img, region, 2.0, 32, 8, 3.0, spacing)
        assert n == 2
        # each peak in its own region, and every isophote pixel assigned
        assert lab[15, 12] != lab[15, 24] and np.all(lab[region] > 0)
    one = _two_blobs(12, 0.0)
    assert _deblend(one, one >= 2.0, 2.0, 32, 8, 3.0, "linear")[1] == 1


def test_deblend_merges_small_regions():
    # A big blob and a one-pixel spike (prominence 27.5) joined by a line of 8 pixels at 2.5:
    # both regions grow along the line at one pixel per step, so the spike's region is the
    # spike and 4 line pixels, fewer than 8, and it is merged.
    img = _two_blobs(0, 0.0)  # one blob at x = 12, above 2 out to x = 18
    img[15, 18:26] = 2.5
    img[15, 26] = 30.0
    region = img >= 2.0
    assert ndimage.label(region, structure=np.ones((3, 3)))[1] == 1
    lab, n = _deblend(img, region, 2.0, 32, 8, 3.0, "linear")
    assert n == 1
    assert _deblend(img, region, 2.0, 32, 1, 3.0, "linear")[1] == 2


def test_bad_input_raises():
    s = [np.zeros((N, N))] * 2
    w = [np.ones((N, N))] * 2
    off = [(0, 0)] * 2
    with pytest.raises(ShearfitValueError):
        analyse_stamps([], [], [], 3.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, w[:1], off, 3.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps([np.zeros((N, N)), np.zeros((N, N - 1))], w, off, 3.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, [np.ones((3, 3))] * 2, off, 3.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, w, [(0, 0, 0)] * 2, 3.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, w, off, 0.0)
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, w, off, 3.0, level_spacing="cubic")
    with pytest.raises(ShearfitValueError):
        analyse_stamps(s, w, off, 3.0, nsigma=-1)


# --- tier 2: GalSim-drawn stamps ---------------------------------------------------------

def _no_masks(res):
    return all(not m.any() for m in res.masks)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_isolated_galaxy(seed):
    rng = np.random.default_rng(seed)
    g = 0.3 * random_direction(rng)
    sim = Sim([(exp_gal(0.4, *g), (0.0, 0.0))], rng)
    res = sim.analyse(30.0, rng)
    assert res.flag == FITCLASS_GALAXY and res.n_regions == 1
    assert _no_masks(res) and all(res.keep_exposure)
    assert len(res.masks) == len(res.keep_exposure) == NEXP
    assert res.isophote[N // 2, N // 2]
    # The galaxy sits at each exposure's offset, so the co-add's light is centred on their
    # mean, the nominal position. Noise-free, the centroid inside the isophote is exact up
    # to the light cut off below the isophote. With noise, blobs joined to the isophote's
    # edge scatter it with long tails (measured per axis: 0.3 pixel at S/N 30, 0.08 at 200
    # with 1 % of cases beyond 0.3 in radius, 0.04 at 500), so 0.3 pixel is tested at 500.
    clean = analyse_stamps(sim.clean, [np.full((N, N), 1e8)] * NEXP, sim.offsets, sim.psf_fwhm_pixels)
    assert math.hypot(*clean.centroid) < 0.01
    assert math.hypot(*sim.analyse(500.0, rng).centroid) < 0.3


def test_centroid_unbiased_at_low_snr():
    # At S/N 30 the isophote's noisy edge scatters the centroid by ~0.3 pixel per axis
    # (measured); over 40 realisations the mean must be within 4 standard errors of zero.
    rng = np.random.default_rng(12)
    sim = Sim([(exp_gal(0.4, 0.2, -0.1), (0.0, 0.0))], rng)
    c = np.array([sim.analyse(30.0, rng).centroid for _ in range(40)])
    err = c.std(axis=0, ddof=1) / math.sqrt(len(c))
    assert np.all(np.abs(c.mean(axis=0)) < 4 * err)
    assert np.all(c.std(axis=0) < 0.5)


@pytest.mark.parametrize("seed", [3, 13, 23])
def test_well_separated_neighbour_is_masked(seed):
    # At twice the smoothed noise the isophotes reach far: chains of noise blobs joined a
    # neighbour 20 pixels away to the target's isophote in ~5 % of trials at S/N 20-30
    # (measured), and one 24 pixels away in under 1 %; the latter is used here.
    rng = np.random.default_rng(seed)
    nb_pos = (17.0, -17.0)
    sim = Sim([(exp_gal(0.3, 0.1, -0.2), (0.0, 0.0)), (galsim.Gaussian(sigma=0.2, flux=0.5), nb_pos)], rng)
    stamps, weights, offsets = sim.observe(20.0, rng)
    res = analyse_stamps(stamps, weights, offsets, sim.psf_fwhm_pixels)
    assert res.flag == FITCLASS_GALAXY and res.n_regions == 1
    assert all(res.keep_exposure)
    mask = res.masks[0]
    assert all(np.array_equal(m, mask) for m in res.masks)  # no shift: the same on every exposure
    nb_pix = pixel_of(offsets, nb_pos)
    assert mask[nb_pix]
    assert not mask[N // 2, N // 2]
    assert not (mask & res.isophote).any()
    # the neighbour's whole 2-sigma isophote is inside its mask, and the mask goes no
    # further than the dilation (2 pixels) beyond it
    snr = smooth_coadd(stamps, weights, sim.psf_fwhm_pixels).snr
    comp, _ = ndimage.label(snr >= 2.0, structure=np.ones((3, 3)))
    nb_iso = comp == comp[nb_pix]
    assert not (nb_iso & res.isophote).any()  # the isophotes do not touch
    assert np.all(mask[nb_iso])
    assert not (mask & ~ndimage.binary_dilation(nb_iso, np.ones((5, 5)))).any()
    # without neighbour masking nothing is masked
    res2 = analyse_stamps(stamps, weights, offsets, sim.psf_fwhm_pixels, neighbour_mask=False)
    assert _no_masks(res2) and res2.flag == FITCLASS_GALAXY


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_overlapping_pair_is_blended(seed):
    # Two compact galaxies 5 pixels apart, fluxes 1 : 0.9, under a 0.5" (2.7-pixel) PSF:
    # smoothed by the PSF, the noise-free image keeps two peaks, the lower standing ~7
    # noise sigmas above the col between them at this S/N, and their isophotes are one.
    rng = np.random.default_rng(seed)
    d = 5.0 * random_direction(rng)
    objs = [(galsim.Gaussian(sigma=0.1, flux=1.0), (0.0, 0.0)), (galsim.Gaussian(sigma=0.1, flux=0.9), tuple(d))]
    sim = Sim(objs, rng, psf_fwhm=0.5)
    stamps, weights, offsets = sim.observe(60.0, rng)
    ideal = smooth_coadd(sim.clean, weights, sim.psf_fwhm_pixels).snr
    comp, _ = ndimage.label(ideal >= 2.0, structure=np.ones((3, 3)))
    region = comp == comp[N // 2, N // 2]
    assert _significant_maxima(np.where(region, ideal, -np.inf), region, 2.0, 6.0).sum() == 2
    res = analyse_stamps(stamps, weights, offsets, sim.psf_fwhm_pixels)
    c2 = pixel_of(offsets, d)
    assert res.isophote[N // 2, N // 2] and res.isophote[c2]  # touching isophotes: one region
    assert res.flag == FITCLASS_BLENDED and res.n_regions == 2
    assert _no_masks(res)  # a blend is not a neighbour: nothing to mask


@pytest.mark.parametrize("prof", [exp_gal(0.5, 0.5, 0.0), galsim.DeVaucouleurs(half_light_radius=0.4).shear(g1=-0.2,
                                                                                                             g2=0.3)],
                         ids=["exponential", "deVaucouleurs"])
def test_single_smooth_galaxy_never_split(prof):
    rng = np.random.default_rng(7)
    sim = Sim([(prof, (0.0, 0.0))], rng)
    for snr in (20.0, 50.0, 100.0, 200.0, 500.0):
        for _ in range(3):
            res = sim.analyse(snr, rng)
            assert res.flag == FITCLASS_GALAXY, (snr, res.reason)
            assert res.n_regions == 1 and _no_masks(res)


def test_bad_column_inside_isophote_drops_exposure():
    rng = np.random.default_rng(8)
    sim = Sim([(exp_gal(0.4, 0.2, 0.1), (0.0, 0.0))], rng)
    stamps, weights, offsets = sim.observe(30.0, rng)
    weights = [w.copy() for w in weights]
    stamps = [s.copy() for s in stamps]
    weights[3][:, N // 2 + 1] = 0.0
    stamps[3][:, N // 2 + 1] = np.nan  # what a masked column may hold
    res = analyse_stamps(stamps, weights, offsets, sim.psf_fwhm_pixels)
    assert res.flag == FITCLASS_GALAXY
    assert res.isophote[:, N // 2 + 1].any()
    assert res.keep_exposure == [i != 3 for i in range(NEXP)]
    # the same column far from the object is just background
    weights[3][:, N // 2 + 1] = weights[0][0, 0]
    stamps[3][:, N // 2 + 1] = 0.0
    weights[3][:, 2] = 0.0
    stamps[3][:, 2] = np.nan
    res = analyse_stamps(stamps, weights, offsets, sim.psf_fwhm_pixels)
    assert not res.isophote[:, 2].any()
    assert all(res.keep_exposure) and res.flag == FITCLASS_GALAXY


@pytest.mark.parametrize("seed", [9, 10])
def test_light_off_the_nominal_position(seed):
    # An extended galaxy (half-light radius 3.2 pixels) whose light is centred 6 pixels from
    # the catalogue position: its isophote still covers that position, but its centroid is
    # beyond the 4-pixel limit. At S/N 100 the centroid scattered by at most 0.55 pixel in
    # 300 trials (measured), so 0.8 pixel is the bound.
    rng = np.random.default_rng(seed)
    d = 6.0 * random_direction(rng)
    sim = Sim([(exp_gal(0.6, 0.1, 0.0), tuple(d))], rng)
    res = sim.analyse(100.0, rng)
    assert res.flag == FITCLASS_CENTROID, res.reason
    assert res.isophote[N // 2, N // 2]
    assert np.allclose(res.centroid, d, atol=0.8)
    # 2 pixels off is accepted
    sim = Sim([(exp_gal(0.6, 0.1, 0.0), tuple(d / 3))], rng)
    res = sim.analyse(100.0, rng)
    assert res.flag == FITCLASS_GALAXY and np.allclose(res.centroid, d / 3, atol=0.8)


@pytest.mark.parametrize("seed", range(5))
def test_noise_only_stamp(seed):
    rng = np.random.default_rng(100 + seed)
    stamps = [rng.normal(0.0, 2.0, (N, N)) for _ in range(NEXP)]
    weights = [np.full((N, N), 0.25)] * NEXP
    res = analyse_stamps(stamps, weights, rng.uniform(-0.5, 0.5, (NEXP, 2)), PSF_FWHM / PIX)
    assert res.flag == FITCLASS_GALAXY and res.n_regions == 0
    assert _no_masks(res) and not res.isophote.any() and all(res.keep_exposure)


def test_no_isophote_still_drops_exposure_with_bad_core():
    rng = np.random.default_rng(11)
    stamps = [rng.normal(0.0, 1.0, (N, N)) for _ in range(3)]
    weights = [np.ones((N, N)) for _ in range(3)]
    weights[1][N // 2, N // 2 + 1] = 0.0  # inside one PSF FWHM of the nominal position
    weights[2][5, 5] = 0.0  # far away
    res = analyse_stamps(stamps, weights, np.zeros((3, 2)), PSF_FWHM / PIX)
    assert res.flag == FITCLASS_GALAXY and res.n_regions == 0
    assert res.keep_exposure == [True, False, True]


# --- tier 3: population statistics (slow) ------------------------------------------------

@pytest.mark.slow
def test_false_blend_rate_on_population():
    # 200 isolated galaxies of the paper's population (sizes, B/T, ellipticities from the
    # priors) at S/N 10-50. With the default min_contrast = 2, 7 and 8 of 1000 were flagged in
    # development; a limit of 3 % (6 of 200) is exceeded by a true rate of 0.7 % with
    # probability 6e-4.
    from shearfit.engine.priors import sample_population
    from shearfit.simulate.stamps import galaxy_profile

    rng = np.random.default_rng(2024)
    pop = sample_population(rng.uniform(21.0, 24.5, 200), rng)
    flagged = 0
    for g in pop:
        prof = galaxy_profile(g.scalelength, g.bulge_fraction, g.e1, g.e2, is_bulge=g.is_bulge)
        res = Sim([(prof, (0.0, 0.0))], rng).analyse(rng.uniform(10.0, 50.0), rng)
        flagged += res.flag != FITCLASS_GALAXY
    assert flagged <= 6


@pytest.mark.slow
def test_resolved_pairs_are_flagged():
    # Compact equal pairs 8 pixels apart at S/N 30 (0.7" PSF) show two clear peaks in the
    # smoothed image; all 30 of 30 were flagged in development. Limit: 24 of 30.
    rng = np.random.default_rng(2025)
    hits = 0
    for _ in range(30):
        d = 8.0 * random_direction(rng)
        objs = [(exp_gal(0.05), (0.0, 0.0)), (exp_gal(0.05), tuple(d))]
        hits += Sim(objs, rng).analyse(30.0, rng).flag != FITCLASS_GALAXY
    assert hits >= 24


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_rotated_and_flipped_exposures_get_the_neighbour_masked_too(seed):
    """The pipeline's co-add carries every exposure onto the first one's grid through the Jacobians.

    Four exposures of a galaxy and a separate neighbour 20 pixels away: the first north-up, the
    others rotated by 50 and 130 degrees and flipped. The neighbour must be masked on each of them
    where it lies on that exposure's own pixels, the galaxy must not be, and a bad column through
    the galaxy drops only the exposure that has it.
    """
    from shearfit.io.fieldconfig import PipelineConfig
    from shearfit.pipeline.driver import _isophote_analysis

    rng = np.random.default_rng(seed)
    nb_sky = np.array([14.0, -14.0]) * PIX            # arcsec (u, v) from the galaxy: 20 pixels
    gal = exp_gal(0.3, 0.1, -0.2, flux=1.0)
    nb = galsim.Gaussian(sigma=0.2, flux=0.5)
    psf = moffat()

    def jac(angle, flip):
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        return PIX * np.array([[-c, s], [s, c]]) @ np.diag([flip, 1.0])

    cuts, nb_only = [], []
    for angle, flip in ((0.0, 1.0), (50.0, 1.0), (0.0, -1.0), (130.0, -1.0)):
        J = jac(angle, flip)
        wcs = galsim.JacobianWCS(J[0, 0], J[0, 1], J[1, 0], J[1, 1])
        off = rng.uniform(-0.5, 0.5, 2)
        p_nb = np.linalg.solve(J, nb_sky)              # the neighbour on this exposure's pixels
        draw = lambda prof, at: galsim.Convolve(prof, psf).drawImage(  # noqa: E731
            nx=N, ny=N, wcs=wcs, use_true_center=False, offset=tuple(off + at), dtype=np.float64).array
        clean = draw(gal, np.zeros(2)) + draw(nb, p_nb)
        nb_only.append(draw(nb, p_nb))
        cuts.append(dict(image=clean, weight=np.ones((N, N)), offset=tuple(off), J=J, k=1,
                         moments=(PSF_FWHM / PIX / 2.3548,), p_nb=p_nb))
    power = math.sqrt(sum(float(np.sum(c["image"] ** 2)) for c in cuts))
    sigma = power / 25.0
    for c in cuts:
        c["image"] = c["image"] + rng.normal(0.0, sigma, (N, N))
        c["weight"] = np.full((N, N), sigma ** -2)
    cuts[1]["weight"][:, N // 2 + 1] = 0.0             # a bad column through the galaxy on exposure 1 only
    pc = PipelineConfig()
    assert _isophote_analysis(cuts, pc) == FITCLASS_GALAXY
    assert [c["keep"] for c in cuts] == [True, False, True, True]
    for k, (c, light) in enumerate(zip(cuts, nb_only)):
        masked = c["weight"] == 0
        masked[:, N // 2 + 1] &= k != 1
        at = np.asarray(c["offset"]) + c["p_nb"]
        row, col = N // 2 + int(round(at[1])), N // 2 + int(round(at[0]))
        assert masked[row, col], k
        assert not masked[N // 2 - 2:N // 2 + 3, N // 2 - 2:N // 2 + 3].any(), k
        # most of the neighbour's light on this exposure falls on masked pixels
        assert light[masked].sum() > 0.9 * light.sum(), k


def _rotated_cuts(rng, objects, angles_flips, snr=40.0):
    """Noisy stamps of ``objects`` ((profile, (u, v) arcsec from the target)) on exposures rotated and flipped
    by ``angles_flips``, as the pipeline cuts them: each with its Jacobian, sub-pixel offset, CCD position
    (x, y) and the objects' positions on its own pixels (``at``: offsets from the target, pixels)."""
    psf = moffat()
    cuts = []
    for k, (angle, flip) in enumerate(angles_flips):
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        J = PIX * np.array([[-c, s], [s, c]]) @ np.diag([flip, 1.0])
        wcs = galsim.JacobianWCS(J[0, 0], J[0, 1], J[1, 0], J[1, 1])
        off = rng.uniform(-0.5, 0.5, 2)
        at = [np.linalg.solve(J, np.asarray(uv, float)) for _, uv in objects]
        img = sum(galsim.Convolve(prof, psf).drawImage(nx=N, ny=N, wcs=wcs, use_true_center=False,
                                                       offset=tuple(off + p), dtype=np.float64).array
                  for (prof, _), p in zip(objects, at))
        cuts.append(dict(e=k, c=0, x=500.0 + off[0], y=700.0 + off[1], image=img, weight=np.ones((N, N)),
                         offset=tuple(off), J=J, k=1, moments=(PSF_FWHM / PIX / 2.3548,), at=at))
    sigma = math.sqrt(sum(float(np.sum(c["image"] ** 2)) for c in cuts)) / snr
    for c in cuts:
        c["image"] = c["image"] + rng.normal(0.0, sigma, (N, N))
        c["weight"] = np.full((N, N), sigma ** -2)
    return cuts


_TURNS = ((0.0, 1.0), (50.0, 1.0), (0.0, -1.0), (130.0, -1.0))


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_a_catalogued_neighbour_inside_the_isophote_flags_a_blend(seed):
    """A pair 0.6" apart (3 pixels) under a 0.7" PSF shows one maximum: the deblender keeps it as one galaxy, and
    the catalogue's second object inside the isophote makes it blended (-3) on rotated and flipped exposures,
    wherever the neighbour is listed (here only on the last, rotated and flipped, exposure's CCD). A neighbour
    masked outside the isophote, or none, leaves it a galaxy."""
    from shearfit.io.fieldconfig import PipelineConfig
    from shearfit.pipeline.driver import _isophote_analysis

    rng = np.random.default_rng(seed)
    pc = PipelineConfig()
    close = 0.6 * random_direction(rng)
    objs = [(exp_gal(0.3, 0.1, -0.2), (0.0, 0.0)), (exp_gal(0.2, flux=0.6), tuple(close))]
    cuts = _rotated_cuts(rng, objs, _TURNS)
    near = [(7, c["e"], 0, c["x"] + c["at"][1][0], c["y"] + c["at"][1][1]) for c in cuts[-1:]]
    assert _isophote_analysis([dict(c) for c in cuts], pc) == FITCLASS_GALAXY   # one maximum: not split
    assert _isophote_analysis([dict(c) for c in cuts], pc, near) == FITCLASS_BLENDED
    # the same neighbour listed on another CCD of that exposure is not on these stamps
    assert _isophote_analysis([dict(c) for c in cuts], pc, [(7, near[0][1], 1) + near[0][3:]]) == FITCLASS_GALAXY
    far = 20.0 * PIX * random_direction(rng)
    cuts = _rotated_cuts(rng, [objs[0], (galsim.Gaussian(sigma=0.2, flux=0.5), tuple(far))], _TURNS)
    near = [(7, c["e"], 0, c["x"] + c["at"][1][0], c["y"] + c["at"][1][1]) for c in cuts]
    assert _isophote_analysis(cuts, pc, near) == FITCLASS_GALAXY
    at = np.asarray(cuts[0]["offset"]) + cuts[0]["at"][1]
    assert cuts[0]["weight"][N // 2 + int(round(at[1])), N // 2 + int(round(at[0]))] == 0   # masked instead


def test_neighbour_positions_reach_the_reference_grid_through_the_jacobians():
    """On an isophote of one pixel, the neighbour listed on each rotated or flipped exposure in turn must land on
    exactly that pixel of the first exposure's grid, and on no other: where that exposure's object lands on the
    grid (the co-add's nearest-pixel carry), plus the neighbour's sky offset in the first exposure's pixels."""
    from shearfit.pipeline.driver import _neighbour_inside

    rng = np.random.default_rng(11)
    sky = np.array([1.3, -0.9])                           # arcsec from the target
    cuts = _rotated_cuts(rng, [(exp_gal(0.3), (0.0, 0.0)), (exp_gal(0.3), tuple(sky))], _TURNS)
    offsets = [np.linalg.solve(cuts[0]["J"], c["J"] @ np.asarray(c["offset"])) for c in cuts]
    for c, off in zip(cuts, offsets):
        p0 = off + cuts[0]["at"][1]
        row, col = N // 2 + int(round(p0[1])), N // 2 + int(round(p0[0]))
        near = [(7, c["e"], 0, c["x"] + c["at"][1][0], c["y"] + c["at"][1][1])]
        for dr, dc in ((0, 0), (1, 0), (0, 1), (-1, 0), (0, -1)):
            iso = np.zeros((N, N), bool)
            iso[row + dr, col + dc] = True
            assert _neighbour_inside(cuts, near, iso, offsets, cuts[0]["J"]) == (dr == dc == 0), (c["e"], dr, dc)


def test_catalogue_neighbours_are_the_objects_within_the_radius_on_a_shared_ccd():
    """Objects 0-1 are 10 pixels apart on CCD 0, 2 is 40 pixels from 1; 3 lies near 0 on CCD 1 only (another
    exposure); 4 is a duplicate row of 2."""
    from shearfit.io.stamps import Locations
    from shearfit.pipeline.driver import catalogue_neighbours

    hits = Locations(object=np.array([0, 0, 1, 2, 3, 4]), ccd=np.array([0, 1, 0, 0, 1, 0]),
                     x=np.array([100.0, 300.0, 110.0, 150.0, 305.0, 150.0]),
                     y=np.array([50.0, 60.0, 50.0, 50.0, 60.0, 50.0]))
    ptr, idx = catalogue_neighbours(hits, 6, 20.0)
    assert [idx[ptr[i]:ptr[i + 1]].tolist() for i in range(6)] == [[1, 3], [0], [4], [0], [2], []]


def test_compiled_nearest_map_is_numpys():
    """The pixel maps between exposures' stamp grids (driver._nearest_map) from the compiled kernel are the numpy
    lines': rotated, stretched and flipped grids on odd and even stamps, half-pixel ties rounded to even alike."""
    from shearfit.engine.kernel import USE_KERNEL
    from shearfit.pipeline.driver import _nearest_map

    if not USE_KERNEL:
        pytest.skip("compiled kernel not built")
    rng = np.random.default_rng(1)
    maps = 0
    for t in range(400):
        a = rng.uniform(-0.2, 0.2)
        A = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * (1 + rng.normal(0, 0.02, (2, 2)))
        if t % 7 == 0:
            A = A[::-1]
        if t % 11 == 0:
            A = np.array([[0.5, 0.0], [0.0, 1.5]])   # ties at every other pixel
        shape = (int(rng.integers(3, 60)), int(rng.integers(3, 60)))
        got, ref = _nearest_map(A, shape), _nearest_map(A, shape, use_kernel=False)
        assert (got is None) == (ref is None)
        if got is not None:
            maps += 1
            assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1]) and got[1].dtype == bool
    assert maps > 300


# --- the compiled isophote analysis against its numpy lines ---------------------------------

def _blobs(rng, shape, n_blobs, quantise=False):
    """Gaussian blobs of random heights and widths on unit noise (rounded to integers: plateaus and ties)."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    img = rng.normal(0.0, 1.0, shape)
    for _ in range(n_blobs):
        cy, cx = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        s = rng.uniform(0.8, 4.0)
        img += rng.uniform(3.0, 60.0) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    return np.round(img) if quantise else img


def _kernel_or_skip():
    from shearfit.engine.kernel import USE_KERNEL

    if not USE_KERNEL:
        pytest.skip("compiled kernel not built")


def test_compiled_deblender_is_numpys():
    """The deblender's compiled loops (significant maxima, growth level by level, amalgamation) give the numpy
    lines' labels exactly: isophotes of one to six blobs on noise, values rounded to integers in a third of them
    (plateaus and ties everywhere), linear and log levels, several region sizes and contrasts."""
    _kernel_or_skip()
    from shearfit.engine.kernel import KERNEL
    from shearfit.pipeline.blends import _pad1

    rng = np.random.default_rng(5)
    multi = strong_many = 0
    for t in range(400):
        shape = (int(rng.integers(6, 40)), int(rng.integers(6, 40)))
        snr = _blobs(rng, shape, int(rng.integers(1, 7)), quantise=t % 3 == 0)
        comp, n = ndimage.label(snr >= 2.0, structure=np.ones((3, 3)))
        if n == 0:
            continue
        region = comp == 1 + int(np.argmax(np.bincount(comp.ravel())[1:]))
        box = ndimage.find_objects(region.astype(np.int8))[0]
        contrast = float(rng.choice([0.0, 1.0, 2.0, 3.0]))
        args = (snr[box], region[box], 2.0, int(rng.choice([2, 5, 32])), int(rng.choice([1, 4, 8])), contrast,
                "log" if t % 4 == 0 else "linear")
        lab, n_reg = _deblend(*args)
        ref_lab, ref_n = _deblend(*args, use_kernel=False)
        assert n_reg == ref_n and np.array_equal(lab, ref_lab), t
        multi += ref_n > 1
        reg = _pad1(region[box])
        v = np.where(reg, _pad1(snr[box]), -np.inf)
        strong = np.empty(reg.shape, dtype=bool)
        count = KERNEL.sig_maxima(v, reg.view(np.uint8), reg.shape[1], 2.0, contrast, strong.view(np.uint8))
        ref = _significant_maxima(v, reg, 2.0, contrast)
        assert count == ref.sum() and np.array_equal(strong, ref), t
        strong_many += count > 2
    assert multi > 40 and strong_many > 20, (multi, strong_many)


def test_compiled_isophote_analysis_is_numpys(monkeypatch):
    """analyse_stamps with its compiled co-add, smoothing and isophote decisions gives the numpy and scipy lines'
    BlendResult exactly: one to eight exposures of blobs on noise, some carried through rotated or stretched
    nearest-pixel maps, bad, NaN, infinite and negative-weight pixels, targets at, beside and off the nominal
    position, neighbour masks grown by 0 to 3 pixels or not asked for."""
    _kernel_or_skip()
    from shearfit.pipeline import blends
    from shearfit.pipeline.driver import _nearest_map

    rng = np.random.default_rng(9)
    seen = {"none": 0, "masked": 0, "blended": 0, "dropped": 0, "mapped": 0}
    for t in range(250):
        n_exp = int(rng.integers(1, 9))
        shape = (int(rng.integers(9, 50)), int(rng.integers(9, 50)))
        base = _blobs(rng, shape, int(rng.integers(0, 5)))
        if t % 2:   # an object near the centre
            yy, xx = np.mgrid[:shape[0], :shape[1]]
            base += rng.uniform(5, 80) * np.exp(-((xx - shape[1] // 2) ** 2 + (yy - shape[0] // 2) ** 2)
                                                / (2 * rng.uniform(1, 3) ** 2))
        stamps, weights, carry = [], [], []
        for e in range(n_exp):
            s = base + rng.normal(0.0, 1.0, shape)
            w = np.full(shape, rng.uniform(0.5, 2.0))
            k = rng.integers(0, 4)
            if k == 1:
                w[rng.random(shape) < 0.02] = 0.0
            elif k == 2:
                s[rng.random(shape) < 0.01] = np.nan
                w[rng.random(shape) < 0.01] = -1.0
            elif k == 3:
                w[rng.random(shape) < 0.01] = np.inf
            stamps.append(s)
            weights.append(w)
            m = None
            if e and rng.random() < 0.4:
                a = rng.uniform(-0.3, 0.3)
                A = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * (1 + rng.normal(0, 0.03, (2, 2)))
                m = _nearest_map(A, shape)
                seen["mapped"] += m is not None
            carry.append(m)
        offsets = rng.uniform(-0.5, 0.5, (n_exp, 2)) + (rng.uniform(-3, 3, 2) if t % 5 == 0 else 0)
        kw = dict(neighbour_mask=bool(t % 4), neighbour_grow=int(rng.integers(0, 4)),
                  min_peak_snr=float(rng.choice([3.0, 5.0])), min_region_pixels=int(rng.choice([4, 8])))
        fwhm = float(rng.uniform(1.5, 5.0))
        got = analyse_stamps(stamps, weights, offsets, fwhm, carry=carry, **kw)
        coadd, inv, bad, _ = blends._stack_coadd(stamps, weights, offsets, carry)
        sc = blends._smoothed(coadd, inv, fwhm)
        with monkeypatch.context() as mp:
            mp.setattr(blends, "USE_KERNEL", False)
            ref = analyse_stamps(stamps, weights, offsets, fwhm, carry=carry, **kw)
            ref_coadd, ref_inv, ref_bad, _ = blends._stack_coadd(stamps, weights, offsets, carry)
            ref_sc = blends._smoothed(ref_coadd, ref_inv, fwhm)
        assert np.array_equal(coadd, ref_coadd) and np.array_equal(inv, ref_inv) and np.array_equal(bad, ref_bad)
        # scipy's correlate1d sums a symmetric kernel's taps in pairs, outermost first; so does the kernel
        for a, b in ((sc.smoothed, ref_sc.smoothed), (sc.noise, ref_sc.noise), (sc.snr, ref_sc.snr)):
            assert np.array_equal(a, b), t
        assert (got.flag, got.reason, got.keep_exposure, got.n_regions) == \
               (ref.flag, ref.reason, ref.keep_exposure, ref.n_regions), t
        assert np.array_equal(got.isophote, ref.isophote) and all(np.array_equal(a, b)
                                                                  for a, b in zip(got.masks, ref.masks))
        assert np.array_equal(got.centroid, ref.centroid, equal_nan=True)
        assert got.peak_snr == ref.peak_snr or (math.isnan(got.peak_snr) and math.isnan(ref.peak_snr))
        seen["none"] += not got.isophote.any()
        seen["masked"] += any(m.any() for m in got.masks)
        seen["blended"] += got.flag == FITCLASS_BLENDED
        seen["dropped"] += not all(got.keep_exposure)
    assert min(seen.values()) >= 10, seen


def test_carried_stamps_take_scalar_weights():
    """Weights given as one value per exposure are carried through a map as the stamps are: the same result as
    the full arrays; a weight of another shape is refused with the stamp's shape named."""
    from shearfit.pipeline.driver import _nearest_map

    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:32, :32]
    clean = 30 * np.exp(-((xx - 16) ** 2 + (yy - 16) ** 2) / 8.0)
    stamps = [clean + rng.normal(0, 1, clean.shape) for _ in range(3)]
    a = 0.2
    carry = [None, _nearest_map(np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]), clean.shape), None]
    one = analyse_stamps(stamps, [1.0] * 3, [(0, 0)] * 3, 3.0, carry=carry)
    full = analyse_stamps(stamps, [np.ones(clean.shape)] * 3, [(0, 0)] * 3, 3.0, carry=carry)
    assert one.flag == full.flag == FITCLASS_GALAXY and one.keep_exposure == full.keep_exposure
    assert np.array_equal(one.isophote, full.isophote) and one.centroid == full.centroid
    with pytest.raises(ShearfitValueError, match="stamp shape"):
        analyse_stamps(stamps, [np.ones(5)] * 3, [(0, 0)] * 3, 3.0, carry=carry)
