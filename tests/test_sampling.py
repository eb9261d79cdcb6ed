"""Adaptive and two-pass ellipticity sampling, and the estimator, on analytic likelihoods.

A stand-in for EllipticityLikelihood returns a 2D Gaussian log-likelihood in
(e1, e2) of known mean and width; with a flat enough prior the likelihood mean
over the samples must return the Gaussian's mean and its 1D variance.
"""

import numpy as np
import pytest

from shearfit.config import FitConfig
from shearfit.engine.sampling import EPoint, adaptive_samples, estimate, lensing_weight, two_pass_samples


class Gaussian:
    def __init__(self, mean, sigma):
        self.mean = np.asarray(mean, float)
        self.sigma = sigma
        self.calls = 0

    def __call__(self, e1, e2):
        e1 = np.atleast_1d(e1)
        e2 = np.atleast_1d(e2)
        self.calls += e1.size
        ll = -0.5 * ((e1 - self.mean[0]) ** 2 + (e2 - self.mean[1]) ** 2) / self.sigma ** 2
        z = np.zeros_like(e1)
        # same likelihood for both populations: the posterior is L x the mixed prior
        return EPoint(logl_disk=ll, logl_bulge=ll, mean_r=z + 0.3, mean_b=z, mean_flux=z + 100.0)


# a wide posterior cut isolates the sampling arithmetic from the prior's pull
CFG = FitConfig(posterior_cut=1e-6)


@pytest.mark.parametrize("sampler", [adaptive_samples, two_pass_samples])
@pytest.mark.parametrize("mean,sigma", [((0.1, -0.05), 0.03), ((0.25, 0.3), 0.08), ((-0.2, 0.1), 0.15)])
def test_mean_and_variance_of_a_gaussian(sampler, mean, sigma):
    like = Gaussian(mean, sigma)
    s = sampler(like, CFG)
    est = estimate(s, CFG)
    # the prior multiplies the posterior only; the likelihood mean is the Gaussian's mean up to
    # the grid's discretisation (exp(-2 pi^2 sigma^2 / h^2) small for sigma >= h/2)
    assert est.e1 == pytest.approx(mean[0], abs=0.02 * sigma + 1e-4)
    assert est.e2 == pytest.approx(mean[1], abs=0.02 * sigma + 1e-4)
    assert est.e_var == pytest.approx(sigma ** 2, rel=0.08)
    assert est.weight == pytest.approx(lensing_weight(est.e_var, CFG))


def test_adaptive_stopping_rule():
    cfg = FitConfig()
    # the rule: refine while fewer than 30 samples are above 5 % of the maximum posterior and the
    # step is above 0.02. (The disk prior's 1/e cusp at the origin, regularised at e0, concentrates
    # the posterior even for a flat likelihood, so a broad likelihood may still refine once.)
    for sigma in (0.3, 0.6):
        s = adaptive_samples(Gaussian((0.0, 0.0), sigma), cfg)
        coarse = np.isclose(np.hypot(s.e1 / 0.16 - np.rint(s.e1 / 0.16), s.e2 / 0.16 - np.rint(s.e2 / 0.16)), 0)
        lp = s.logpost - s.logpost.max()
        refined = s.e1.size > coarse.sum()
        n0 = (lp[coarse] > s.logpost[coarse].max() - s.logpost.max() + np.log(0.05)).sum()
        assert refined == (n0 < cfg.n_above)
        assert (lp > np.log(0.05)).sum() >= cfg.n_above or min(s.area[s.area > 0]) == pytest.approx(0.02 ** 2)
    # narrow: refinement down to 0.02 (never finer)
    narrow = adaptive_samples(Gaussian((0.13, -0.07), 0.01), cfg)
    assert min(narrow.area[narrow.area > 0]) == pytest.approx(0.02 ** 2)
    lp = narrow.logpost - narrow.logpost.max()
    assert np.all(np.hypot(narrow.e1, narrow.e2) < cfg.model_e_limit)
    # intermediate: stops as soon as 30 samples are above 5 %
    mid = adaptive_samples(Gaussian((0.1, 0.1), 0.05), cfg)
    lp = mid.logpost - mid.logpost.max()
    assert (lp > np.log(0.05)).sum() >= cfg.n_above or min(mid.area[mid.area > 0]) == pytest.approx(0.02 ** 2)


def test_posterior_cut_rejects_low_prior_tail():
    """Samples whose posterior is under 1 % of its maximum do not enter the mean (sec. 3.4)."""
    cfg = FitConfig()
    like = Gaussian((0.0, 0.0), 0.6)          # nearly flat: the prior alone shapes the posterior
    s = adaptive_samples(like, cfg)
    est = estimate(s, cfg)
    keep = s.logpost > s.logpost.max() + np.log(cfg.posterior_cut)
    assert est.n_used == keep.sum() < s.e1.size
    # the disk prior vanishes at e_max = 0.804: nothing beyond it survives except through the bulge prior
    assert np.all(np.hypot(s.e1[keep], s.e2[keep]) < 0.98)


def test_refinement_follows_the_posterior_not_its_bounding_box():
    """Each halving samples only the lattice within one old step of the samples above the posterior
    cut: no finest-level sample lies farther than that from them (a bounding box of a round posterior
    would add its corners, far below the cut), and the estimate is the Gaussian's mean."""
    cfg = FitConfig()
    s = adaptive_samples(Gaussian((0.1, 0.05), 0.04), cfg)
    fine = np.isclose(s.area, 0.02 ** 2)
    assert fine.sum() > 30
    lp = s.logpost - s.logpost.max()
    top = lp > np.log(cfg.posterior_cut) - 1.0
    cheb = np.max(np.abs(np.stack([s.e1[fine][:, None] - s.e1[top][None, :],
                                   s.e2[fine][:, None] - s.e2[top][None, :]])), axis=0).min(axis=1)
    assert cheb.max() <= 0.04 + 1e-9
    est = estimate(s, cfg)
    assert abs(est.e1 - 0.1) < 0.01 and abs(est.e2 - 0.05) < 0.01


@pytest.mark.parametrize("mean,sigma", [((0.1, -0.05), 0.01), ((0.37, 0.29), 0.03), ((-0.2, 0.1), 0.15),
                                        ((0.6, -0.55), 0.05)])
def test_coarse_prepass_keeps_every_sample_the_estimator_uses(mean, sigma):
    """With e_grid_prepass the 0.16 start grid is sampled only near the coarse samples within the margin of
    the posterior cut: the samples above the cut, their cells and so the estimate are those of the paper's
    full start grid, for fewer likelihood evaluations."""
    paper, pre = FitConfig(e_grid_prepass=0.0), FitConfig()
    assert pre.e_grid_prepass == 0.32
    la, lb = Gaussian(mean, sigma), Gaussian(mean, sigma)
    a, b = adaptive_samples(la, paper), adaptive_samples(lb, pre)
    assert lb.calls < la.calls

    def used(s, cfg):
        keep = s.logpost > s.logpost.max() + np.log(cfg.posterior_cut)
        return sorted(zip(np.round(s.e1[keep], 9), np.round(s.e2[keep], 9), np.round(s.area[keep], 12)))

    assert used(a, paper) == used(b, pre)
    ea, eb = estimate(a, paper), estimate(b, pre)
    assert ea.e1 == pytest.approx(eb.e1, abs=1e-12) and ea.e2 == pytest.approx(eb.e2, abs=1e-12)
    assert ea.e_var == pytest.approx(eb.e_var, rel=1e-9)


def test_prepass_must_be_a_power_of_two_of_the_start():
    from shearfit.errors import ShearfitValueError

    FitConfig(e_grid_prepass=0.64)
    FitConfig(e_grid_prepass=0.0)
    for bad in (0.24, 0.16, 0.08):
        with pytest.raises(ShearfitValueError, match="e_grid_prepass"):
            FitConfig(e_grid_prepass=bad)


@pytest.mark.parametrize("settings", [{}, {"disk_e_max": 0.7, "disk_e0": 0.05, "bulge_e_b": 3.0}])
def test_the_samplers_lattice_priors_are_the_priors_at_its_points(settings):
    """The sampler takes the ellipticity priors of its lattice points from one table per set of the priors'
    settings: the same numbers as the priors evaluated at those points, and another table for other settings."""
    from shearfit.engine import priors
    from shearfit.engine.sampling import _lattice_log_priors

    cfg = FitConfig(**settings)
    unit, half = cfg.e_grid_min, 120
    pd, pb = _lattice_log_priors(cfg, unit, half)
    rng = np.random.default_rng(3)
    i, j = rng.integers(-half, half + 1, (2, 400))
    e1, e2 = i.astype(float) * unit, j.astype(float) * unit
    with np.errstate(divide="ignore"):
        assert np.array_equal(pd[i + half, j + half], np.log(priors.disk_e_density(e1, e2, cfg)))
        assert np.array_equal(pb[i + half, j + half], np.log(priors.bulge_e_density(e1, e2, cfg)))
    assert np.isneginf(pd[half + 45, half]) and np.isfinite(pd[half + 30, half])   # zero beyond e_max
    if settings:
        assert not np.array_equal(pd, _lattice_log_priors(FitConfig(), unit, half)[0])


def test_replays_take_the_lattice_priors_at_lattice_points_and_compute_the_others():
    """A replay's samples (a fit's lattice points) take their priors from the lattice's table: the same numbers as
    computed; ellipticities that are not exactly lattice points (or lie beyond the table) are computed."""
    from shearfit.engine.sampling import _known_log_e_priors, _lattice_half, _log_e_priors

    cfg = FitConfig(e_grid_min=0.005)
    unit, half = cfg.e_grid_min, _lattice_half(cfg)
    rng = np.random.default_rng(4)
    i, j = rng.integers(-150, 151, (2, 300))
    e1, e2 = i.astype(float) * unit, j.astype(float) * unit
    got, want = _known_log_e_priors(e1, e2, cfg), _log_e_priors(e1, e2, cfg)
    assert all(np.array_equal(g, w) for g, w in zip(got, want))
    for a, b in ((e1 + 1e-12, e2), (e1, np.full_like(e2, (half + 1) * unit))):   # off the lattice; beyond it
        got, want = _known_log_e_priors(a, b, cfg), _log_e_priors(a, b, cfg)
        assert all(np.array_equal(g, w) for g, w in zip(got, want))


def test_store_points_are_the_steps_lattice_points_in_the_mask():
    """_Store._points looks only at the step's rows and columns of a region's box: the same points, in the
    same order, as a search of every lattice point of the box (boxes at any corner, steps 1-64)."""
    from shearfit.engine.sampling import _Store

    cfg = FitConfig()
    st = _Store(None, cfg)
    rng = np.random.default_rng(4)
    limit = cfg.model_e_limit / st.unit
    for _ in range(60):
        step = int(rng.choice([1, 2, 4, 8, 16, 32, 64]))
        i0, j0 = (int(v) for v in rng.integers(-60, 40, 2))
        mask = rng.random(tuple(int(v) for v in rng.integers(1, 90, 2))) < 0.6
        want = [(i0 + a, j0 + b) for a in range(mask.shape[0]) for b in range(mask.shape[1])
                if mask[a, b] and (i0 + a) % step == 0 and (j0 + b) % step == 0
                and (i0 + a) ** 2 + (j0 + b) ** 2 < limit * limit]
        assert st._points(step, i0, j0, mask) == want
        assert st.regions[-1][0] == step and st.regions[-1][3] is mask


@pytest.mark.parametrize("r,e,bulge", [(0.2, (0.5, 0.0), True), (0.4, (0.0, 0.8), False), (0.4, (0.56, 0.56), False)])
def test_located_sizes_reach_the_size_peak(r, e, bulge):
    """benchmarks/size_locate.py's check on a noise-free pure bulge and two elongated disks at SNR 200: along the
    fit's e, the likelihood with each sample's size located by the fit's passes is within 1 nat of the one with its
    size nodes on the dense size peak, wherever it lies within 20 nats of its best (session 74: up to 218 nats
    short for the disks, whose round fit the pure-bulge population wins, and 6-7 nats for the bulge)."""
    from scripts import load_script

    bench = load_script("benchmarks/size_locate.py", "size_locate_bench")
    obs = bench.observations(r, e, bulge, 200.0, np.random.default_rng(3))
    ae, short, located = bench.shortfall(obs, 22.0, FitConfig(disk_e_max=0.95))
    assert located
    assert abs(ae - np.hypot(*e)) < 0.03
    assert np.nanmax(np.abs(short)) < 1.0, short


@pytest.mark.skipif(not __import__("shearfit.engine.kernel", fromlist=["USE_KERNEL"]).USE_KERNEL,
                    reason="needs the compiled kernel")
def test_located_size_peaks_compiled_and_numpy_agree_to_the_bit():
    """The size-locating parabolas in C (locate_parabola) against the numpy lines: the same peak values and
    offsets to the bit, with non-finite log L (the -1e300 floor), NaN, ties between nodes and between the two
    populations, peaks at either end (held off the end nodes) and parabolas that open upwards."""
    from types import SimpleNamespace

    from shearfit.engine.sampling import EllipticityLikelihood

    rng = np.random.default_rng(4)
    nrow, n = 400, 5
    xs = np.linspace(-0.6, 0.6, n)
    ld = rng.normal(-50.0, 8.0, nrow * n)
    lb = rng.normal(-50.0, 8.0, nrow * n)
    ld[rng.random(ld.size) < 0.05] = -np.inf
    lb[rng.random(lb.size) < 0.05] = np.nan
    lb[:20] = ld[:20]                                     # the populations tie
    ld[100:140] = np.repeat(rng.normal(-40, 1, 8), 5)     # every node tied
    lpr = rng.normal(0.0, 2.0, (nrow, n))
    lpr[7, 3] = np.nan
    mg = SimpleNamespace(logl_disk=ld, logl_bulge=lb)
    w = (np.log(0.9), np.log(0.1))
    with np.errstate(invalid="ignore"):
        got = EllipticityLikelihood._parabola_peaks(mg, *w, lpr, xs, (nrow, n))
        ref = EllipticityLikelihood._parabola_peaks(mg, *w, lpr, xs, (nrow, n), use_kernel=False)
    for a, b in zip(got, ref):
        assert np.array_equal(a, b, equal_nan=True)


def _near_cut_case(change, n=81, sigma=0.08):
    """A reference's samples on a grid with a Gaussian log posterior, and an evaluate() giving ``nv`` versions the
    reference's plus change(v, e1, e2), recording what was evaluated."""
    from types import SimpleNamespace

    g = np.linspace(-0.4, 0.4, n)
    e1, e2 = [a.ravel() for a in np.meshgrid(g, g)]
    ref = SimpleNamespace(e1=e1, e2=e2, logpost=-0.5 * (e1 ** 2 + e2 ** 2) / sigma ** 2)
    vals = {}

    def evaluate(which, versions, need=None):
        rows = np.flatnonzero(which)
        for j, v in enumerate(versions):
            at = rows if need is None else rows[need[:, j]]
            lp = vals.setdefault(v, np.full(e1.size, -np.inf))
            lp[at] = ref.logpost[at] + change(v, e1[at], e2[at])

    return ref, evaluate, (lambda v, which: vals[v][which]), vals


@pytest.mark.parametrize("first_margin", [0.25, 0.5, 1.0])
def test_replays_leave_out_only_samples_their_change_keeps_below_the_cut(first_margin):
    """_evaluate_near_cut with a first margin: every sample above a version's own cut is evaluated, the samples its
    smooth change keeps well below the cut are not; where the change is not what the first samples predict (a step
    beyond them), the version evaluates the whole margin; with too few samples above the cut, the whole margin."""
    from shearfit.engine.sampling import _evaluate_near_cut

    cfg = FitConfig()
    lnc = np.log(cfg.posterior_cut)

    def check(change, nv, expect_whole):
        ref, evaluate, logpost_of, vals = _near_cut_case(change)
        ok = np.ones(ref.e1.size, bool)
        full = ref.logpost > ref.logpost.max() + lnc - 10.0
        sel = _evaluate_near_cut(ref, ok, cfg, 10.0, first_margin, nv, evaluate, logpost_of)
        for v in range(nv):
            true = ref.logpost + change(v, ref.e1, ref.e2)
            above = full & (true > true[full].max() + lnc)
            assert np.all(sel[v][above]), v                   # every sample of the version's estimate
            assert np.isfinite(vals[v][sel[v]]).all() and not np.isfinite(vals[v][~sel[v]]).any()
            if expect_whole[v]:
                assert np.array_equal(sel[v], full), v
            else:
                assert sel[v].sum() < 0.6 * full.sum(), (v, sel[v].sum(), full.sum())
        # no sample evaluated that the version does not need: beyond the reference's own above its cut, which every
        # version evaluates, each lies within the first margin (and the fits' allowance) of the version's own cut
        # (not another's: the versions evaluated together each make only their own)
        ref_above = ref.logpost > ref.logpost.max() + lnc
        for v in range(nv):
            true = ref.logpost + change(v, ref.e1, ref.e2)
            need = true > true[full].max() + lnc - first_margin - 3.0
            if not expect_whole[v]:
                assert not np.any(sel[v] & ~ref_above & ~need), v

    # metacal-like: a small shift of the peak, each version its own
    smooth = lambda v, e1, e2: (-1) ** v * (8.0 * e1 + 3.0 * e2 * (v + 1)) + 0.5 * v * e1 * e2   # noqa: E731
    check(smooth, 3, [False, False, False])
    # version 1 lifts everything beyond the first samples by 4 nats, which their fit cannot see: the samples it
    # evaluates next to them show it, and it takes the whole margin
    step = lambda v, e1, e2: smooth(v, e1, e2) + (v == 1) * 4.0 * (np.hypot(e1, e2) > 0.244)   # noqa: E731
    check(step, 2, [False, True])
    # a narrow posterior: fewer samples above the cut than the prediction needs
    ref, evaluate, logpost_of, vals = _near_cut_case(smooth, sigma=0.005)
    ok = np.ones(ref.e1.size, bool)
    full = ref.logpost > ref.logpost.max() + lnc - 10.0
    assert (ref.logpost > ref.logpost.max() + lnc).sum() < 12
    sel = _evaluate_near_cut(ref, ok, cfg, 10.0, first_margin, 2, evaluate, logpost_of)
    assert all(np.array_equal(s, full) for s in sel)
