"""Measure one object on many exposures: the public single-object API."""

from __future__ import annotations

import contextlib
import gc
import hashlib
from dataclasses import dataclass, replace
from typing import Iterable, Mapping, Sequence

import numpy as np
from scipy import special

from . import priors
from ..config import as_config
from ..errors import (FITCLASS_CENTROID, FITCLASS_FEW_EXPOSURES, FITCLASS_FIT_FAILED, FITCLASS_GALAXY,
                     FITCLASS_STAR, FITCLASS_TOO_LARGE, ShearfitValueError)
from .likelihood import (coarse_peak, find_position, flux_position_marginal, join_exposures, model_sums,
                         seed_round_bins, shift_joint)
from .model import complex_bincount, prepare_exposures, shape_matrix
from ..observation import FitResult, Observation
from .profiles import de_vaucouleurs, exponential_disk, fast_pair
from .sampling import (EllipticityLikelihood, Samples, VersionLikelihoods, adaptive_samples, adaptive_versions,
                       estimate, log_population_weights, replay_samples, replay_versions, two_pass_samples)

__all__ = ["measure_object", "measure_objects", "measure_versions", "FitPlan", "paused_gc"]

# free parameters of the galaxy (e1, e2, x, y, r, S, B) and of a point source (x, y, S)
_NPAR_GALAXY = 7
_NPAR_STAR = 3




def _size_range(jm, cfg, mag, fast):
    """Where the round model's size posterior lies in ln r: its median and its 0.1 % and 99.9 % points, and the
    median of the disk population's alone.

    Quantiles of the posterior on a fine grid move continuously with the data
    (nodes that jumped with a small change of the data would make the
    estimator respond unevenly to shear) and follow a skewed posterior's tail
    towards r = 0, which small galaxies have.
    """
    a = float(priors.size_prior_scale(mag, cfg))
    pix = jm.pixel_scale
    r = np.geomspace(0.01 * min(a, pix), 12.0 * max(a, pix), 64)
    z = np.zeros_like(r)
    mg = flux_position_marginal(model_sums(jm, z, z, r, fast, cfg.bulge_size_ratio, bins_per_octave=cfg.mode_bins_per_octave),
                                cfg, jm.pixel_scale)
    ld0, lb0 = log_population_weights(cfg)
    logl = np.logaddexp(ld0 + mg.logl_disk, lb0 + mg.logl_bulge)
    # posterior density in ln r: likelihood x prior x r
    x = np.log(r)
    lpr = priors.log_size_prior_per_lnr(x, mag, cfg)
    lp = logl + lpr
    if not np.any(np.isfinite(lp)):
        return None
    lo, med, hi = _quantiles(lp, x, [1e-3, 0.5, 1 - 1e-3])
    lp_disk = mg.logl_disk + lpr
    med_disk = _quantiles(lp_disk, x, [0.5])[0] if np.any(np.isfinite(lp_disk)) else med
    return float(med), float(lo), float(hi), float(med_disk)


def _quantiles(lp, x, q):
    """Quantiles ``q`` in x of the density exp(lp) on the grid x: the cumulative distribution, linear between
    grid points, inverted."""
    w = np.exp(lp - np.nanmax(lp))
    w = np.where(np.isfinite(w), w, 0.0)
    c = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(x))])
    c /= c[-1]
    return np.interp(q, c, x)


def _size_likelihood(jm, cfg, mag, fast, rng):
    """The likelihood of ellipticity with its size nodes placed from ``rng`` (:func:`_size_range`'s median,
    0.1 % and 99.9 % points in ln r).

    Spline nodes uniform in ln r from the round model's 0.1 % to its 99.9 % point (plus a margin), carried to
    each ellipticity by the predicted growth of the best size with e; where that range is narrower than the
    +-15 % uncertainty of the prediction, passes of 5 nodes over +-0.6 and then +-0.15 first locate the peak at
    each ellipticity.

    The passes start halfway (in ln r) between the sizes predicted from the round model's median and from its
    disk population's. Where the pure-bulge population wins the round fit, its size is 1.5-1.8 times the disk
    population's, and the elliptical models' best size may follow either: a pure bulge's the first, an elongated
    disk's the second (which the round fit of a disk at |e| 0.7-0.85 can put below the bulge's, depending on its
    orientation). Started from the round model's alone, the passes could not reach an elongated disk's size at
    |e| above about 0.7 (r 0.4", SNR 170: the likelihood there 10-180 nats low, e 0.03-0.08 low in |e|; session
    74). Where the disk population wins, the two medians agree and so do the starts.
    """
    med, lo, hi, med_disk = rng
    margin_x = 0.1
    x = np.linspace(lo - med - margin_x, hi - med + margin_x, cfg.n_size)
    locate = (0.6, 0.15) if (hi - lo) < 1.2 else None
    return EllipticityLikelihood(jm, cfg, mag, fast, x, float(np.exp(med)), locate_widths=locate,
                                 locate_from=float(np.exp(0.5 * (med + med_disk))))


@contextlib.contextmanager
def paused_gc():
    """Python's cyclic garbage collector paused for one fit (a context manager), as it was before afterwards: a
    fit makes and drops thousands of small containers, whose collection rounds (each also walking the older
    generations in turn) cost a few per cent of it, and leaves little cyclic garbage (collected once the
    collector runs again)."""
    was = gc.isenabled()
    if was:
        gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def measure_object(observations: Sequence[Observation], mag: float, config=None,
                   return_samples: bool = False, noise_seed=None) -> FitResult:
    """Measure the ellipticity of one object jointly on all its exposures.

    Parameters
    ----------
    observations : sequence of :class:`Observation`
        The object's stamps, one per exposure, with PSF, Jacobian, offset and
        photometric scale each.
    mag : float
        The object's magnitude: it sets the size prior (App. B.1).
    config : FitConfig or mapping, optional
        Settings (defaults: the paper's).
    return_samples : bool
        Attach the ellipticity samples (``result.samples``: a structured array
        with e1, e2, area, logl, logpost).
    noise_seed : int or sequence of int, optional
        With the ``noise_bias_correction`` setting, the seed of the noise it
        adds (:func:`noise_bias_noise`); by default one made from the pixels.

    Returns
    -------
    FitResult
        A single unmeasurable object gives a result with a negative
        ``fitclass`` and a ``message``, never an exception.
    """
    cfg = as_config(config)
    observations = list(observations)
    if any(not isinstance(o, Observation) for o in observations):
        raise ShearfitValueError("measure_object takes a sequence of shearfit.Observation")
    obs = [o for o in observations if o.weight.size and o.weight.max() > 0]   # (weights: finite, >= 0)
    if not obs:
        return FitResult(fitclass=FITCLASS_FEW_EXPOSURES, message="no usable exposure")
    try:
        with paused_gc():
            res, plan = _measure(obs, float(mag), cfg, return_samples)
            if cfg.self_calibration and plan is not None and res.fitclass >= FITCLASS_GALAXY:
                _self_calibrate(obs, float(mag), cfg, res, plan)
            if cfg.noise_bias_correction and plan is not None and res.fitclass >= FITCLASS_GALAXY:
                _correct_noise_bias(obs, float(mag), cfg, res, noise_seed, plan)
        return res
    except (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError, ValueError) as exc:
        if isinstance(exc, ShearfitValueError):
            raise
        return FitResult(fitclass=FITCLASS_FIT_FAILED, n_exposures_used=len(obs), message=f"fit failed: {exc}")


@dataclass
class FitPlan:
    """The choices a fit makes from its object's data, for replaying on other versions of the object.

    ``keep``: per exposure, the Fourier modes kept by the noise-aware cut;
    ``decoupled``: per fold group, whether its cross terms were dropped;
    ``shift``: the sky offset (du, dv) of the cross-correlation peak;
    ``size_nodes`` and ``r_center``: the ln r spline nodes and the round
    model's size; ``centres``: the size centre used at each ellipticity
    sample; ``samples``: the ellipticity samples, their cells and posterior;
    ``observations`` and ``exposures``: the fitted observations and their
    Fourier modes, which a version with the same PSFs, Jacobians and offsets
    reuses (only its pixels are transformed).
    """

    keep: list
    shift: tuple
    size_nodes: np.ndarray
    r_center: float
    centres: Mapping   # sampling.SizeCentres (a dict made at its first look)
    samples: Samples
    observations: list = None   # the fitted observations and their ExposureModes, whose modes a version
    exposures: list = None      # with the same PSFs, Jacobians and offsets reuses
    joint: object = None        # the fit's JointModes (merged, shifted), whose structure such a version reuses
    decoupled: object = None    # per fold group, whether its cross terms were dropped (JointModes.decoupled)


def _same_modes(o: Observation, ref: Observation) -> bool:
    """Whether two observations reduce to the same Fourier modes (all but the pixel data equal)."""
    return (o.shape == ref.shape and o.psf_oversampling == ref.psf_oversampling and o.psf_moffat == ref.psf_moffat
            and o.flux_scale == ref.flux_scale and (o.offset is ref.offset or np.array_equal(o.offset, ref.offset))
            and (o.jacobian is ref.jacobian or np.array_equal(o.jacobian, ref.jacobian))
            and (o.psf is ref.psf or np.array_equal(o.psf, ref.psf)))


def _position_search(mag, cfg, pix):
    """The round reference model's size and the largest offset of the cross-correlation peak (arcsec)."""
    return min(float(priors.size_prior_scale(mag, cfg)), 2 * pix), cfg.max_centroid_shift * pix


def _measure(obs, mag, cfg, return_samples, plan=None, margin=np.inf, first_margin=None, own_position=False,
             own_samples=False, own_sizes=False):
    """One object's fit: (FitResult, the FitPlan it made, or None where it stopped early).

    With ``plan``, the fit replays another version's choices (modes, position, size nodes and centres,
    ellipticity samples within ``margin`` nats of its posterior cut) instead of making its own; with
    ``own_position`` as well, it finds its own position from the plan's (:func:`_replay_likelihood`); with
    ``own_samples``, its own ellipticity grid (:func:`shearfit.engine.sampling.adaptive_versions`); with
    ``own_sizes``, its own size nodes and centres (:func:`_replay_likelihood`).
    """
    fast = fast_pair(cfg.truncation)
    exposures = prepare_exposures(obs, cfg) if plan is None else _replay_exposures(obs, cfg, plan)
    if plan is None:
        disk = exponential_disk(cfg.truncation)
        jm = join_exposures(exposures, cfg.mode_chi2_tolerance, fold_tolerance=cfg.fold_chi2_tolerance,
                            pair_tolerance=cfg.pair_chi2_tolerance)
        pix = jm.pixel_scale
        r_ref, max_shift = _position_search(mag, cfg, pix)
        start = coarse_peak(exposures, [o.jacobian for o in obs], disk, r_ref, 2 * max_shift, pix, keep=jm.keep)
        du, dv, ok = find_position(jm, disk, r_ref, max_shift, start=start)
        shift = float(np.hypot(du, dv))
        if not ok or shift > max_shift:
            return _off_centre(obs, shift, pix), None
        jm = shift_joint(jm, du, dv)
        rng = _size_range(jm, cfg, mag, fast)
        if rng is None:
            return FitResult(fitclass=FITCLASS_FIT_FAILED, n_exposures_used=len(obs), centroid_shift=shift / pix,
                             message="no model correlates with the data"), None
        like = _size_likelihood(jm, cfg, mag, fast, rng)
        samples = adaptive_samples(like, cfg) if cfg.sampling == "adaptive" else two_pass_samples(like, cfg)
        n_samples = samples.e1.size
        plan = FitPlan(keep=jm.keep, shift=(du, dv), size_nodes=like.x, r_center=like.r_center, centres=like.centres,
                       samples=samples, observations=list(obs), exposures=exposures, joint=jm, decoupled=jm.decoupled)
    else:
        jm, like, shift = _replay_likelihood(exposures, mag, cfg, plan, own_position, own_sizes)
        if like is None:
            return _off_centre(obs, shift, jm.pixel_scale), plan
        if own_samples:
            samples = adaptive_versions(VersionLikelihoods([like]), plan.samples, cfg, margin, first_margin)[0]
        else:
            samples = replay_samples(like, plan.samples, cfg, margin, first_margin)
        return _replayed_result(obs, cfg, mag, jm, like, samples, shift, return_samples), plan
    return _result(obs, cfg, mag, jm, like, samples, n_samples, shift / pix, return_samples), plan


def _replay_exposures(obs, cfg, plan):
    """The Fourier modes of a version of the object ``plan`` was made from (its modes reused where the
    version's observations reduce to the same)."""
    if plan.exposures is not None and len(plan.observations) == len(obs):
        return prepare_exposures(obs, cfg, likes=[ex if _same_modes(o, r) else None
                                                  for o, r, ex in zip(obs, plan.observations, plan.exposures)])
    return prepare_exposures(obs, cfg)


def _replay_exposures_versions(versions, cfg, plan):
    """:func:`_replay_exposures` of every version (lists of observations of one length), as one
    :func:`shearfit.engine.model.prepare_exposures` call: their stamps' transforms made together (the same numbers).
    None where that fails (each version then prepares its own, so that a failure is that version's)."""
    n = len(versions[0])
    if plan.exposures is None or len(plan.observations) != n:
        return None
    likes = [ex if _same_modes(o, r) else None for obs in versions
             for o, r, ex in zip(obs, plan.observations, plan.exposures)]
    try:
        flat = prepare_exposures([o for obs in versions for o in obs], cfg, likes=likes)
    except _FIT_ERRORS as exc:
        if isinstance(exc, ShearfitValueError):
            raise
        return None
    return [flat[i * n:(i + 1) * n] for i in range(len(versions))]


def _off_centre(obs, shift, pix):
    return FitResult(fitclass=FITCLASS_CENTROID, n_exposures_used=len(obs), centroid_shift=shift / pix,
                     message="cross-correlation peak too far from the input position")


#: A version's own cross-correlation peak within this many pixels of the plan's is the plan's (the Newton
#: search stops on steps below it, so the peak is known to no better; identical stamps then give the fit itself).
SAME_POSITION = 1e-6


def _replay_likelihood(exposures, mag, cfg, plan, own_position=False, own_sizes=False):
    """(joint modes, likelihood, centroid shift in arcsec) of a version that replays ``plan`` (its modes, size
    nodes and centres); the likelihood is None where the version's own peak lies too far away.

    With ``own_position``, the version's position is its own cross-correlation peak (:func:`find_position`
    from the plan's, which is the version's position where the two agree to ``SAME_POSITION`` pixels) rather
    than the plan's: the estimate then also follows the position's response to the version's pixels, as a
    fit of its own would (metacal's responses, ``benchmarks/README.md``, session 45). Every other choice
    is replayed but, with ``own_sizes``, the size nodes and centres: the version places its own from its
    round model's size posterior (:func:`_size_range`, as the fit does), so that the estimate's response
    through the size integral's quadrature is part of the differences too (the plan's where that fails).
    """
    jm, shift, ok = _replay_joint(exposures, mag, cfg, plan, own_position)
    if not ok:
        return jm, None, float(np.hypot(*shift))
    return (jm,) + _replay_like(jm, mag, cfg, plan, own_sizes, shift)


def _replay_joint(exposures, mag, cfg, plan, own_position=False):
    """:func:`_replay_likelihood`'s joint modes: (jm, (du, dv) the position's shift, whether the version's own
    peak lies near enough)."""
    if plan.keep is not None and [k.size for k in plan.keep] != [e.kx.size for e in exposures]:
        raise ShearfitValueError("a replayed fit needs the same PSFs (Fourier modes) as the fit it replays")
    # the same modes (PSFs, Jacobians, offsets and noise): only the data's weights z change
    same = plan.joint is not None and plan.exposures is not None and len(plan.exposures) == len(exposures) \
        and all(e.kx is r.kx for e, r in zip(exposures, plan.exposures))
    jm = plan.joint.with_data(exposures) if same else None
    if jm is None:
        jm = shift_joint(join_exposures(exposures, keep=plan.keep, decoupled=plan.decoupled,
                                        pair_tolerance=cfg.pair_chi2_tolerance), *plan.shift)
    du, dv = plan.shift
    if own_position:
        # the peak relative to the plan's (these modes are already moved there), found as the fit finds its own
        r_ref, max_shift = _position_search(mag, cfg, jm.pixel_scale)
        ddu, ddv, ok = find_position(jm, exponential_disk(cfg.truncation), r_ref, np.inf)
        shift = float(np.hypot(du + ddu, dv + ddv))
        if not ok or shift > max_shift:
            return jm, (du + ddu, dv + ddv), False
        if np.hypot(ddu, ddv) > SAME_POSITION * jm.pixel_scale:
            jm = shift_joint(jm, ddu, ddv)
            du, dv = du + ddu, dv + ddv
    return jm, (du, dv), True


def _replay_like(jm, mag, cfg, plan, own_sizes, shift):
    """:func:`_replay_likelihood`'s likelihood and centroid shift (arcsec) on the version's joint modes ``jm``
    (:func:`_replay_joint`'s, with its ``shift``)."""
    du, dv = shift
    fast = fast_pair(cfg.truncation)
    rng = _size_range(jm, cfg, mag, fast) if own_sizes else None
    if rng is not None:
        return _size_likelihood(jm, cfg, mag, fast, rng), float(np.hypot(du, dv))
    like = EllipticityLikelihood(jm, cfg, mag, fast, plan.size_nodes, plan.r_center)
    like.fixed_centres = plan.centres
    return like, float(np.hypot(du, dv))


def _replayed_result(obs, cfg, mag, jm, like, samples, shift, return_samples=False):
    return _result(obs, cfg, mag, jm, like, samples, int(np.count_nonzero(samples.evaluated)),
                   shift / jm.pixel_scale, return_samples)


def _result(obs, cfg, mag, jm, like, samples, n_samples, centroid_shift, return_samples):
    """The estimate, the star/galaxy test and the size check of one fit, as a FitResult."""
    pix = jm.pixel_scale
    est = estimate(samples, cfg)
    # star/galaxy: F-ratio of the best galaxy (r > 0) against the best point source (sec. 3.2)
    z = like.zero   # the point source, already evaluated for the size integral
    chi2_star = jm.yy + float(min(z.chi2_disk[0], z.chi2_bulge[0]))
    chi2_gal = jm.yy + like.best_chi2_gal
    dof = max(jm.npix - _NPAR_GALAXY, 1)
    allowance = (like.best_snr * cfg.star_psf_error) ** 2 if np.isfinite(like.best_snr) else 0.0
    fstat = max(chi2_star - chi2_gal - allowance, 0.0) / (_NPAR_GALAXY - _NPAR_STAR) / max(chi2_gal / dof, 1e-12)
    # the F distribution's survival function: scipy.stats.f.sf is this ufunc behind argument handling that costs
    # more than it (fstat >= 0 or NaN, where the two agree)
    pvalue = float(special.fdtrc(_NPAR_GALAXY - _NPAR_STAR, dof, fstat))
    is_star = pvalue > cfg.star_pvalue and mag <= cfg.star_faint_limit
    result = FitResult(
        e1=est.e1, e2=est.e2, e_var=est.e_var,
        weight=0.0 if is_star else est.weight,
        snr=like.best_snr, scalelength=est.scalelength, bulge_fraction=est.bulge_fraction,
        model_flux=est.model_flux, fitclass=FITCLASS_STAR if is_star else FITCLASS_GALAXY,
        n_exposures_used=len(obs), star_pvalue=pvalue, centroid_shift=centroid_shift,
        n_samples=n_samples, round_scalelength=est.round_scalelength,
        flux_snr=est.model_flux * float(np.sqrt(max(like.point_ff, 0.0))))
    if not np.isfinite(est.e1):
        result.fitclass = FITCLASS_FIT_FAILED
        result.weight = 0.0
        result.message = "likelihood surface empty"
    else:
        # the truncated model must fit in the stamp, or its Fourier image wraps around (sec. 3.6)
        half_stamp = min(min(o.shape) for o in obs) / 2.0
        extent = cfg.truncation * max(1.0, cfg.bulge_size_ratio) * est.scalelength / pix
        if extent > half_stamp:
            result.fitclass = FITCLASS_TOO_LARGE
            result.weight = 0.0
            result.message = f"truncated model ({extent:.1f} pixels) larger than half the stamp ({half_stamp:.0f})"
    result.shape_weight = est.weight
    result.n_models = int(like.n_models)
    if return_samples:
        rec = np.zeros(samples.e1.size, dtype=[("e1", "f8"), ("e2", "f8"), ("area", "f8"), ("logl", "f8"),
                                               ("logpost", "f8")])
        for f in rec.dtype.names:
            rec[f] = getattr(samples, f)
        result.samples = rec
    return result


def _moved_transfers(plan: "FitPlan"):
    """Each exposure's transfer function times the phase that puts the model at the fit's position
    (``plan.shift``), made once per plan (the self-calibration renders several models on it)."""
    moved = plan.__dict__.get("_moved")
    if moved is None:
        du, dv = plan.shift
        moved = plan._moved = [ex.transfer * np.exp(-1j * (ex.kx * du + ex.ky * dv)) for ex in plan.exposures]
    return moved


def model_observations(obs, plan: "FitPlan", params, cfg):
    """``obs`` with their pixels replaced by the noise-free model ``params`` = (e1, e2, scalelength,
    bulge_fraction, flux) at the fit's position (``plan.shift``): the fit's own model, on each exposure's
    Fourier modes as the fit made them (``plan.exposures``: PSF, pixel, App. A correction, Jacobian, offset,
    flux scale) and transformed to the stamp's pixels, periodic on the stamp as the fit's model is.

    The same numbers as ``model.model_ft`` of each component on the exposures moved to the fit's position, made
    with less of its work repeated: the phase once per plan, rho^2 once for both components where they have one
    size, the sum over the folded modes by bincount."""
    e1, e2, r, b, flux = params
    disk = exponential_disk(cfg.truncation)
    bulge = de_vaucouleurs(cfg.truncation)
    c11, c12, c22 = shape_matrix(e1, e2)
    rb = r * cfg.bulge_size_ratio
    out = []
    for o, ex, transfer in zip(obs, plan.exposures, _moved_transfers(plan)):
        ny, nx = ex.shape
        n = ny * (nx // 2 + 1)
        q = c11 * ex.kx ** 2 + 2 * c12 * ex.kx * ex.ky + c22 * ex.ky ** 2
        rho2 = r * r * q
        M = (1.0 - b) * complex_bincount(ex.coarse, transfer * disk.ft_rho2(rho2), n).reshape(ny, nx // 2 + 1)
        if b != 0:
            rho2b = rho2 if rb == r else rb * rb * q
            M = M + b * complex_bincount(ex.coarse, transfer * bulge.ft_rho2(rho2b), n).reshape(ny, nx // 2 + 1)
        out.append(o.with_image(np.fft.fftshift(np.fft.irfft2(M, s=ex.shape)) * flux))
    return out


#: The largest step of the finite difference that finds the estimator's radial response (self_calibration):
#: wide enough to see the response's trend over the sampler's lattice (0.02 apart), narrow enough to stay
#: local; the step is at most twice the likelihood's width, within which the replayed samples lie.
SELFCAL_STEP = 0.05
#: The largest response the self-calibration divides by (the smallest is the setting self_calibration_min_response).
SELFCAL_MAX_RESPONSE = 1.5
#: The self-calibration's further Newton steps (``self_calibration_steps``) are damped by how well each contracted
#: the residual |f(e) - e_hat|: with q the ratio of a step's residual to the last one's, the next step is scaled by
#: the product over the steps so far of (0.7 - q) / (0.7 - 0.3), within [0, 1], and the steps end where it reaches 0.
#: Near a solution the steps shrink the residual 3 to 30 times and go on undamped; a step that shrinks it less has
#: met the sampler's floor (a residual of about 1e-4, f being measured on the lattice of ellipticity samples) or an
#: estimate f cannot reach (a broad likelihood whose noise-free estimate stays short of the data's at every |e| below
#: the model's limit), and the steps after it fade. Undamped, on 0.1-0.125" galaxies at SNR 100-200, 4 steps carried
#: 3.8 % of the objects (one-step |e| 0.54-0.86) by 0.1-0.3, most to the limit, and those made all of the +0.013 by
#: which the steps moved m (benchmarks/README.md, session 58); at SNR 10-40, by up to 0.44. The damping is a
#: continuous function of the residuals, so the result moves smoothly with the pixels: session 58's rule (go on while
#: a step halves the residual, else keep the iterate of the smallest) stopped the two members of 36 % of the +g / -g
#: pairs of a ring at different steps, and their unconverged residuals became scatter in m (session 60).
SELFCAL_DAMPING = (0.3, 0.7)
#: Once an iterate of the self-calibration's solve lies on the other side of the solution along |e| than an earlier
#: one (the radial residual (f(e) - e_hat) . u changed sign), the latest iterates on the two sides bracket it: each
#: further step is the secant over the last step where it lands between them, else the secant to the other side
#: (false position), else the midpoint, and is taken whole.
#: Without it a first step that overshot a solution where f flattens (a broad likelihood, |e_hat| beyond the knee
#: of f) had its residual grow, the damping stopped the solve there, and the estimate kept the overshoot.
SELFCAL_BRACKETS = True


def _self_calibrate(obs, mag, cfg, res, plan, margin=10.0):
    """Correct ``res``'s ellipticity for the estimator's bias, found on noise-free images of models.

    f(e): the estimate on the noise-free image of the model of ellipticity e (with the fit's posterior-mean
    size, bulge fraction and flux, at its position; :func:`model_observations`), measured as the data were
    (same exposures, weights, modes, position and ellipticity samples). The corrected estimate solves
    f(e) = e_hat, the data's estimate, by Newton steps from e_hat (``self_calibration_steps``, one by default;
    each further step evaluates f at the last solution, takes the secant over the last step as the radial response
    and is damped by how well the last contracted the residual: SELFCAL_DAMPING): the bias
    b = f(e_hat) - e_hat divided by f's response, radially the finite difference of f over min(SELFCAL_STEP,
    2 sigma_e) towards e = 0 and tangentially |f(e_hat)| / |e_hat| (an estimator that turns with the galaxy),
    each bounded to [self_calibration_min_response, SELFCAL_MAX_RESPONSE]. For a small galaxy at high |e| the radial
    response is well below 1 (0.15-0.4 for scalelengths of 0.1-0.125" at |e| 0.6-0.75), and where the bound cuts it
    the bias left is the larger for it.
    """
    e_hat = np.array([res.e1, res.e2])
    a = float(np.hypot(*e_hat))

    def f(e):
        models = model_observations(obs, plan, (e[0], e[1], res.scalelength, res.bulge_fraction, res.model_flux),
                                    cfg)
        ref, _ = _measure(models, mag, cfg, False, plan=plan, margin=margin)
        return np.array([ref.e1, ref.e2])

    u = e_hat / a if a > 1e-6 else np.array([1.0, 0.0])
    v = np.array([-u[1], u[0]])
    # the model's estimate must lie within the data's samples that the replay evaluates: at most 2 sigma_e away
    h = float(np.clip(2.0 * np.sqrt(res.e_var), 0.5 * cfg.e_grid_min, SELFCAL_STEP))
    h = h if a > h else -h
    f0 = f(e_hat)
    fb = f(e_hat - h * u)
    if not (np.all(np.isfinite(f0)) and np.all(np.isfinite(fb))):
        res.fitclass = FITCLASS_FIT_FAILED
        res.weight = 0.0
        res.message = "self-calibration: no estimate on the model's image"
        return
    lo, hi = float(cfg.self_calibration_min_response), SELFCAL_MAX_RESPONSE
    r_rad = float(np.dot(f0 - fb, u) / h)
    r_tan = float(np.dot(f0, u) / a) if a > 0 else np.nan
    s_rad = float(np.clip(r_rad, lo, hi))
    s_tan = float(np.clip(r_tan, lo, hi)) if a > abs(h) else s_rad
    b = f0 - e_hat
    # the models stay within model_e_limit; the estimate may go on beyond it to corrected_e_limit
    out_limit = _corrected_limit(cfg)
    e_out = _within(e_hat - (np.dot(b, u) / s_rad) * u - (np.dot(b, v) / s_tan) * v, out_limit)
    # more steps of the same Newton solve (self_calibration_steps), radially with the secant over the last step,
    # each damped by how well the last contracted the residual |f(e) - e_hat| (SELFCAL_DAMPING): the result moves
    # smoothly with the pixels, and an estimate f cannot reach is not carried towards the model's limit
    steps = 1
    resid = float(np.hypot(*b))
    w = 1.0
    e_prev, f_prev = e_hat, f0
    # the last iterate (e, f(e)) on each side of the solution along u: its radial residual (f(e) - e_hat) . u
    # positive, and negative (SELFCAL_BRACKETS)
    sides = {float(np.sign(np.dot(b, u))): (e_hat, f0)}
    for _ in range(int(cfg.self_calibration_steps) - 1):
        # beyond the models' limit (corrected_e_limit above model_e_limit) f is measured on the limit, and the
        # step from there goes on along f's last secant, damped as every further step
        e_eval = _within(e_out, cfg.model_e_limit)
        f1 = f(e_eval)
        if not np.all(np.isfinite(f1)):
            break
        b = f1 - e_hat
        r1 = float(np.hypot(*b))
        side = float(np.sign(np.dot(b, u)))
        other = sides.get(-side) if SELFCAL_BRACKETS and side != 0.0 else None
        if other is None:   # no iterate on the other side of the solution: damped by the contraction
            q = r1 / resid if resid > 0 else np.inf
            w *= float(np.clip((SELFCAL_DAMPING[1] - q) / (SELFCAL_DAMPING[1] - SELFCAL_DAMPING[0]), 0.0, 1.0))
            if w <= 0.0:
                break
        s_last = _secant(e_eval, f1, e_prev, f_prev, u, s_rad, lo, hi)
        radial = np.dot(b, u)
        if other is None:
            s_rad, step = s_last, w
        else:
            # bracketed: the secant over the last step where it lands between the two sides, else the secant to
            # the other side (false position), else halfway; taken whole
            a0, a1 = float(np.dot(other[0], u)), float(np.dot(e_eval, u))

            def inside(x):
                return min(a0, a1) < x < max(a0, a1)

            land = a1 - radial / s_last
            if not inside(land):
                land = a1 - radial / _secant(e_eval, f1, other[0], other[1], u, s_rad, lo, hi)
            if not inside(land):   # f falls between them (no slope within the bounds crosses)
                land = 0.5 * (a0 + a1)
            s_rad, step = radial / (a1 - land), 1.0
        e_prev, f_prev = e_eval, f1
        sides[side] = (e_eval, f1)
        resid = r1
        e_out = _within(e_eval - step * ((radial / s_rad) * u + (np.dot(b, v) / s_tan) * v), out_limit)
        steps += 1
    res.selfcal_steps = steps
    res.selfcal_de = (float(e_hat[0] - e_out[0]), float(e_hat[1] - e_out[1]))
    res.selfcal_response = (r_rad, r_tan)
    res.e1, res.e2 = float(e_out[0]), float(e_out[1])


def _secant(e1, f1, e0, f0, u, default, lo, hi):
    """f's radial response between e0 and e1 (their secant along u), bounded to [lo, hi]; ``default`` where
    the two lie within 1e-6 of each other along u."""
    de = float(np.dot(e1 - e0, u))
    return float(np.clip(np.dot(f1 - f0, u) / de, lo, hi)) if abs(de) > 1e-6 else default


def _corrected_limit(cfg):
    """The largest |e| of a corrected estimate: corrected_e_limit, and never below model_e_limit."""
    return max(float(cfg.corrected_e_limit), float(cfg.model_e_limit))


def _within(e, limit):
    """``e`` scaled back onto the circle ``|e| = limit`` if beyond it."""
    n = float(np.hypot(*e))
    return e * (limit / n) if n > limit else e


def noise_bias_noise(observations: Sequence[Observation], seed=None) -> list:
    """The noise field that ``noise_bias_correction`` adds to and subtracts from each observation's pixels:
    normal deviates of variance 1 / weight where the weight is positive, 0 elsewhere, drawn exposure after
    exposure from ``numpy.random.default_rng(seed)``. ``seed`` None makes one from the pixels and weights, so
    that an object's correction is reproducible."""
    if seed is None:
        h = hashlib.blake2b(digest_size=8)
        for o in observations:
            h.update(np.ascontiguousarray(o.image).tobytes())
            h.update(np.ascontiguousarray(o.weight).tobytes())
        seed = int.from_bytes(h.digest(), "little")
    rng = np.random.default_rng(seed)
    out = []
    for o in observations:
        w = np.asarray(o.weight, float)
        sd = np.where(w > 0, 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), 0.0)
        out.append(sd * rng.standard_normal(w.shape))
    return out


def _noise_bias_on_model(obs, mag, cfg, res, noise, plan):
    """``noise_bias_on_model``: the noise bias b = (e(m + n) + e(m - n)) / 2 - e(m) of the fit's own model m
    (:func:`model_observations` of the estimate ``res``: its ellipticity within model_e_limit, its size, bulge
    fraction and flux, at its position), each e a full fit with ``cfg`` less noise_bias_correction; None where
    one of them failed (``res`` then says so)."""
    e = _within(np.array([res.e1, res.e2]), cfg.model_e_limit)
    models = model_observations(obs, plan, (e[0], e[1], res.scalelength, res.bulge_fraction, res.model_flux), cfg)
    sub = replace(cfg, noise_bias_correction=False)
    out = []
    for sign in (0.0, 1.0, -1.0):
        r = measure_object([m.with_image(m.image + sign * n) if sign else m for m, n in zip(models, noise)], mag,
                           sub)
        if r.fitclass < FITCLASS_GALAXY or not (np.isfinite(r.e1) and np.isfinite(r.e2)):
            res.fitclass = FITCLASS_FIT_FAILED
            res.weight = 0.0
            res.message = (f"noise-bias correction: the fit of the model's image{' with noise' if sign else ''} "
                           f"failed ({r.message or r.fitclass})")
            return None
        out.append(np.array([r.e1, r.e2]))
    return 0.5 * (out[1] + out[2]) - out[0]


def _correct_noise_bias(obs, mag, cfg, res, seed, plan=None):
    """Noise-bias extrapolation (``noise_bias_correction``): ``res``'s estimate e(y) less
    b = (e(y + n) + e(y - n)) / 2 - e(y), the fits of y +- n made with every other setting as ``res``'s.

    To second order in the noise, the estimate's mean is e0 + B s^2 for pixel noise of variance s^2; y +- n
    has variance 2 s^2, so the pair's mean is e0 + 2 B s^2 on average, while the first-order effect of n
    cancels between its two signs: b estimates B s^2, and e(y) - b is free of the noise bias to that order
    (what is left is of fourth order, -2 C s^4 where C s^4 is the bias's next term).

    With ``noise_bias_second_amplitude`` a (positive, not 1), a second pair y +- a n (the same n) gives the
    fourth-order term too. With the mean e0 + B v + C v^2 at noise variance v s^2, D(t) = ((e(y + t n) +
    e(y - t n)) / 2 - e(y)) / t^2 has the mean B + 2 C + C t^2 (the pair adds t^2 s^2 of variance to data that
    already carry s^2), so C = (D(a) - D(1)) / (a^2 - 1) and e0 = e(y) - B - C = e(y) - D(1) + 2 C. The leading
    fluctuation of D(t), n's quadratic form in the estimate's second derivative, is the same at every t and
    enters with the coefficient 1 as in the one-pair correction; a fit's own discrete jumps (samples crossing
    the cut, modes kept or dropped) enter D(t) divided by t^2, so an a above 1 amplifies them least (a = sqrt(2):
    e0 = 3 e(y) - 3 e(2) + e(3) in the variance's multiples, Richardson's extrapolation).
    """
    noise = noise_bias_noise(obs, seed)
    if cfg.noise_bias_on_model:
        b = _noise_bias_on_model(obs, mag, cfg, res, noise, plan)
        b_one = b
    else:
        b, b_one = _extrapolated_noise_bias(obs, mag, cfg, res, noise)
    if b is None:
        return
    e = np.array([res.e1, res.e2])
    limit = _corrected_limit(cfg)
    e_out = _within(e - b, limit)
    # what was subtracted, the limit's scaling included, so that e + noise_bias_de is the uncorrected estimate
    res.noise_bias_de = tuple(float(x) for x in e - e_out)
    res.noise_bias_de_one_pair = tuple(float(x) for x in e - _within(e - b_one, limit))
    res.e1, res.e2 = float(e_out[0]), float(e_out[1])


def _extrapolated_noise_bias(obs, mag, cfg, res, noise):
    """The extrapolation's bias b and the one pair's D(1) (:func:`_correct_noise_bias`); (None, None) where a
    fit with the added noise failed (``res`` then says so)."""
    sub = replace(cfg, noise_bias_correction=False)
    a = float(cfg.noise_bias_second_amplitude)
    levels = (1.0, a) if a > 0 else (1.0,)
    e = np.array([res.e1, res.e2])
    d = []
    for amp in levels:
        pair = []
        for sign in (1.0, -1.0):
            r = measure_object([o.with_image(o.image + (sign * amp) * n) for o, n in zip(obs, noise)], mag, sub)
            if r.fitclass < FITCLASS_GALAXY or not (np.isfinite(r.e1) and np.isfinite(r.e2)):
                res.fitclass = FITCLASS_FIT_FAILED
                res.weight = 0.0
                res.message = (f"noise-bias correction: the fit with added noise (amplitude {amp:g}) failed "
                               f"({r.message or r.fitclass})")
                return None, None
            pair.append((r.e1, r.e2))
        d.append((0.5 * (np.array(pair[0]) + np.array(pair[1])) - e) / amp ** 2)
    b = d[0]
    if a > 0:
        b = d[0] - 2.0 * (d[1] - d[0]) / (a * a - 1.0)
    return b, d[0]


def measure_versions(versions: Sequence[Sequence[Observation]], mag: float, config=None,
                     margin: float = 10.0, first_margin: float = None, own_position: bool = False,
                     own_samples: bool = False, own_sizes: bool = False) -> list:
    """Measure versions of one object (its stamps slightly transformed, as metacalibration's) alike.

    The first version is fitted as :func:`measure_object` fits it; every
    other one replays the choices that fit made from its data (the Fourier
    modes kept, the size nodes and centres, and the ellipticity samples and
    cells, see :func:`shearfit.engine.sampling.replay_samples`; and, unless
    ``own_position``, the position), so that differences between the
    versions' estimates follow the differences between their pixels
    smoothly. With ``own_position`` each version finds its own position,
    from the first's, as a fit of its own would (the peak moves smoothly
    with the pixels), so that the estimate's response through its position
    is part of the differences too. With ``own_samples`` each version runs
    the adaptive ellipticity grid on its own likelihood (the reference's
    samples evaluated for all versions together,
    :func:`shearfit.engine.sampling.adaptive_versions`), so that the
    estimate's response through its grid is part of them as well (metacal
    at low SNR, ``benchmarks/README.md``, session 46). With ``own_sizes`` each
    version places its own size nodes and centres from its own round model's
    size posterior (:func:`_replay_likelihood`). The versions must carry the
    same PSFs, Jacobians and weights. ``margin`` and ``first_margin``: which samples a replay evaluates
    (:func:`shearfit.engine.sampling.replay_samples`). The replays are evaluated together where the versions
    share the first's Fourier modes (:class:`shearfit.engine.sampling.VersionLikelihoods`), each version's
    estimate that of its own replay to rounding. Returns one FitResult per version.
    """
    cfg = as_config(config)
    if own_samples and cfg.sampling != "adaptive":
        raise ShearfitValueError("measure_versions: own_samples needs sampling: adaptive "
                                 f"(the config has sampling: {cfg.sampling})")
    versions = [list(v) for v in versions]
    if not versions or any(any(not isinstance(o, Observation) for o in v) for v in versions):
        raise ShearfitValueError("measure_versions takes a sequence of sequences of shearfit.Observation")
    if len({len(v) for v in versions}) != 1:
        raise ShearfitValueError("measure_versions: every version needs the same exposures")
    usable = [i for i, o in enumerate(versions[0]) if o.weight.size and o.weight.max() > 0]
    versions = [[v[i] for i in usable] for v in versions]
    if not usable:
        return [FitResult(fitclass=FITCLASS_FEW_EXPOSURES, message="no usable exposure") for _ in versions]
    try:
        with paused_gc():
            res, plan = _measure(versions[0], float(mag), cfg, False, margin=margin, first_margin=first_margin)
    except _FIT_ERRORS as exc:
        if isinstance(exc, ShearfitValueError):
            raise
        res, plan = _failed(versions[0], exc), None
    if plan is None:   # nothing to replay: the reference stopped before sampling
        return [res] + [measure_object(v, mag, cfg) for v in versions[1:]]
    with paused_gc():
        return [res] + _replay_all(versions[1:], float(mag), cfg, plan, margin, first_margin, own_position,
                                   own_samples, own_sizes)


_FIT_ERRORS = (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError, ValueError)


def _failed(obs, exc):
    return FitResult(fitclass=FITCLASS_FIT_FAILED, n_exposures_used=len(obs), message=f"fit failed: {exc}")


def _replay_all(versions, mag, cfg, plan, margin, first_margin, own_position, own_samples=False, own_sizes=False):
    """The versions' replays of ``plan``, their likelihoods evaluated together
    (:class:`shearfit.engine.sampling.VersionLikelihoods`: the same numbers as one replay after another, which
    is what a version whose setup fails, and every version where the joint evaluation fails, gets)."""
    ready, joints, out = [], [], [None] * len(versions)
    together = _replay_exposures_versions(versions, cfg, plan)
    for k, obs in enumerate(versions):
        try:
            exposures = together[k] if together is not None else _replay_exposures(obs, cfg, plan)
            jm, shift, ok = _replay_joint(exposures, mag, cfg, plan, own_position)
            if ok:
                joints.append((k, obs, jm, shift))
            else:
                out[k] = _off_centre(obs, float(np.hypot(*shift)), jm.pixel_scale)
        except _FIT_ERRORS as exc:
            if isinstance(exc, ShearfitValueError):
                raise
            out[k] = _failed(obs, exc)
    # the versions' round bins (their point sources', and own_sizes' round models') made in one binning
    seed_round_bins([j[2] for j in joints], cfg.mode_bins_per_octave)
    for k, obs, jm, shift in joints:
        try:
            like, shift = _replay_like(jm, mag, cfg, plan, own_sizes, shift)
            ready.append((k, obs, jm, like, shift))
        except _FIT_ERRORS as exc:
            if isinstance(exc, ShearfitValueError):
                raise
            out[k] = _failed(obs, exc)
    if not ready:
        return out
    try:
        likes = VersionLikelihoods([r[3] for r in ready])
        samples = (adaptive_versions(likes, plan.samples, cfg, margin, first_margin) if own_samples
                   else replay_versions(likes, plan.samples, cfg, margin, first_margin))
        for (k, obs, jm, like, shift), s in zip(ready, samples):
            out[k] = _replayed_result(obs, cfg, mag, jm, like, s, shift)
    except _FIT_ERRORS as exc:
        if isinstance(exc, ShearfitValueError):
            raise
        for k, obs, *_ in ready:   # one at a time, so that one version's failure is its own
            try:
                out[k] = _measure(obs, mag, cfg, False, plan=plan, margin=margin, first_margin=first_margin,
                                  own_position=own_position, own_samples=own_samples, own_sizes=own_sizes)[0]
            except _FIT_ERRORS as exc2:
                if isinstance(exc2, ShearfitValueError):
                    raise
                out[k] = _failed(obs, exc2)
    return out


def _measure_one(args):
    obs, mag, cfg = args
    return measure_object(obs, mag, cfg)


#: a forked worker's tasks, inherited from the parent (:func:`measure_objects`), which then sends indices only
_FORKED_TASKS = None


def _set_forked_tasks(tasks):
    global _FORKED_TASKS
    _FORKED_TASKS = tasks


def _measure_forked(i):
    return _measure_one(_FORKED_TASKS[i])


def measure_objects(objects: Iterable[Sequence[Observation]], mags, config=None, progress=False, processes=1):
    """Batched form of :func:`measure_object`: one result per object, in input order.

    Parameters
    ----------
    objects : iterable of sequences of :class:`Observation`
    mags : float or array
        One magnitude per object (or one for all).
    config : FitConfig or mapping, optional
    progress : bool
        Show a progress bar.
    processes : int
        Worker processes; results do not depend on it. With one, the objects are measured in this
        process with its BLAS held to one thread (restored after), as each worker's is.
    """
    cfg = as_config(config)
    objects = list(objects)
    mags = np.broadcast_to(np.asarray(mags, float), (len(objects),))
    tasks = [(o, float(m), cfg) for o, m in zip(objects, mags)]
    if processes and processes > 1:
        from ..workers import mp_context, process_pool

        # chunks of a 32nd of a worker's share: at the end one worker waits for the other's last chunk, on average
        # half of one (an 8th: 2 workers x1.79-1.83 over 300 galaxies, a 32nd: x1.89-1.95, benchmarks/speed.py)
        chunk = max(1, len(tasks) // (32 * processes))
        if mp_context().get_start_method() == "fork":
            # the workers inherit the tasks and are sent their indices: an object's 7 stamps, weights and PSFs
            # pickled (0.3 ms), sent (390 kB) and unpickled (0.3 ms) were 4 % of its fit, the parent's share on a
            # core the workers need
            pool_ctx, fn, items = process_pool(processes, _set_forked_tasks, (tasks,)), _measure_forked, range(len(tasks))
        else:
            pool_ctx, fn, items = process_pool(processes), _measure_one, tasks
        with pool_ctx as pool:
            it = pool.imap(fn, items, chunksize=chunk)
            if progress:
                from tqdm import tqdm
                it = tqdm(it, total=len(tasks), desc="measuring")
            return list(it)
    from ..workers import single_threaded

    it = tasks
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=len(tasks), desc="measuring")
    # one BLAS thread, as in a worker (restored after): more threads cost CPU time and save no wall time
    with single_threaded():
        return [_measure_one(t) for t in it]
