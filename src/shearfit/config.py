"""Settings of the shape-measurement engine, with the paper's values as defaults.

Every number that the lensfit paper (Miller et al. 2013, "the paper" below)
fixes is a default here, with the section or equation it comes from. The
object is immutable and is written into every output for provenance.

A YAML config (docs/interface.rst) may set any of these at its top level; an
unknown key is an error that names it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from .errors import ShearfitKeyError, ShearfitValueError

__all__ = ["FitConfig", "fit_config_from_mapping", "as_config", "describe", "setting", "check_choices", "coerce_setting",
           "settings_from_items"]


def setting(default, help, ref="", choices=None):
    """A dataclass field for one setting: its default, help text, paper reference and allowed values.

    Every settings schema of shearfit (:class:`FitConfig`, the field pipeline's
    ``PipelineConfig``) declares its fields with this, and
    :func:`coerce_setting` checks values against them.
    """
    return field(default=default, metadata={"help": help, "ref": ref, "choices": choices})


@dataclass(frozen=True)
class FitConfig:
    """Settings of the per-object likelihood engine.

    Each field's ``metadata`` holds its help text and paper reference; use
    :func:`describe` to list them.
    """

    # --- ellipticity priors (appendix B.2) -----------------------------------
    disk_e_max: float = setting(0.804, "maximum disk ellipticity of the disk prior", "eq. (edisk), App. B")
    disk_e0: float = setting(0.0256, "circularity parameter e0 of the disk prior", "eq. (edisk)")
    disk_e_a: float = setting(0.2539, "dispersion a of the disk prior", "eq. (edisk)")
    bulge_e_b: float = setting(2.368, "b of the bulge ellipticity prior p(e) ~ e exp(-b e - c e^2)", "eq. (ebulge)")
    bulge_e_c: float = setting(6.691, "c of the bulge ellipticity prior", "eq. (ebulge)")

    # --- bulge fraction and populations (sec. 3.2, App. B.3) ------------------
    bulge_population_fraction: float = setting(
        0.1, "f_B, fraction of bulge-dominated (pure de Vaucouleurs) galaxies", "sec. 3.2")
    bulge_fraction_mean: float = setting(0.0, "B0 of the truncated-Gaussian B/T prior of disk galaxies", "eq. (bulgeprior)")
    bulge_fraction_sigma: float = setting(0.1, "sigma_B of the B/T prior", "eq. (bulgeprior)")

    # --- size prior (App. B.1) ------------------------------------------------
    size_lnrd_intercept: float = setting(-1.145, "ln(r_d/arcsec) at the pivot magnitude", "App. B.1")
    size_lnrd_slope: float = setting(-0.269, "d ln(r_d) / d mag", "App. B.1")
    size_pivot_mag: float = setting(23.0, "pivot magnitude of the size relation", "App. B.1")
    size_alpha: float = setting(4.0 / 3.0, "alpha of p(r) ~ r exp(-(r/a)^alpha)", "App. B.1")
    size_rd_over_a: float = setting(
        0.833,
        "r_d/a as the paper writes it (a = r_d/0.833). The true median of p(r) is 1.134 a; "
        "set size_prior_scale='median' to make r_d the prior's exact median instead",
        "App. B.1",
    )
    size_prior_scale: str = setting("paper", "'paper': a = r_d/size_rd_over_a; 'median': a such that median(r) = r_d",
                                 "App. B.1", ("paper", "median"))
    size_prior_axis: str = setting(
        "major", "which scalelength of an elliptical model the size prior is evaluated at: 'major' (the paper's: "
        "the semi-major axis, which the models keep fixed), 'area' (r sqrt(q), the round model of the same area) or "
        "'minor' (r q); a diagnostic of the small-galaxy bias (benchmarks/small_galaxy_bias.py), not a calibration",
        "App. B.1", ("major", "area", "minor"))

    # --- flux prior (sec. 3.2) --------------------------------------------------
    flux_prior_slope: float = setting(2.0, "alpha of the flux prior P(S) ~ S^-alpha", "sec. 3.2")

    # --- galaxy models (sec. 3.1, App. A) ---------------------------------------
    truncation: float = setting(
        4.5, "truncation radius in scalelengths (disk) / half-light radii (bulge), major axis", "sec. 3.1")
    bulge_size_ratio: float = setting(1.0, "bulge half-light radius / disk scalelength", "sec. 3.1")

    # --- position marginalisation (sec. 3.2) ------------------------------------
    delta_chi2_crit: float = setting(6.0, "Delta chi^2 that defines r_max of the position integral", "sec. 3.2")
    max_centroid_shift: float = setting(4.0, "largest accepted position offset of the fitted centre, pixels", "sec. 3.6")
    position_max_step: float = setting(
        1.0, "largest step, pixels, of each model's second-order move from the reference position to its own "
        "cross-correlation peak: the quadratic expansion holds only near the reference, and an extreme-ellipticity "
        "model whose reference lies on the flank of its peak (curvature near zero, gradient large) was credited "
        "with up to 34 nats it does not have when allowed max_centroid_shift (benchmarks/position_step.py; "
        "benchmarks/README.md, session 52)",
        "sec. 3.2 (implementation)")

    # --- flux and size marginalisation (sec. 3.2) -------------------------------
    n_flux: int = setting(7, "flux values per (e, r) for the spline integral (over +-flux_halfwidth sigma; of 80 "
                       "galaxies at SNR 7-15, 11 moves e from 7 by 7e-4 on one measured at SNR 5, 1.3 % of its "
                       "error, and by at most 7e-5 on the others: benchmarks/speed.py --check --check-each)",
                       "sec. 3.2")
    flux_halfwidth: float = setting(5.0, "half-width of the flux samples in units of the flux error", "sec. 3.2")
    n_size: int = setting(7, "scalelengths r > 0 sampled for the size spline (r = 0 is added), uniform in ln r over "
                       "the round model's size posterior (outside-model galaxies against 41 nodes: 7 move e by rms 4.7 "
                       "% of its error at target SNR 7-10, at most 0.97 of it; 21 by 0.8 %, at 1.3 times the cost; "
                       "7 against 21 at SNR 20-40: 1.2 %, benchmarks/README.md session 50)", "sec. 3.2")
    tail_skip: float = setting(
        40.0, "a sample whose last size-locating pass peaks this far (nats) below the highest so far is far "
        "beyond the posterior cut (-4.6): its size integral is that pass's 5 nodes' instead of its size nodes' spline "
        "(0: evaluate every sample fully)", "implementation")
    size_reuse_distance: float = setting(
        0.0, "a sample this close in e to one whose size peak was located starts from it and runs only the narrowest "
        "locating pass (0: locate every sample). Where the size posterior has two peaks the reused one can be the "
        "other (0.12 moved e by 5e-4 on 1 of 40 galaxies, benchmarks/speed.py --check, for 3 % less time)",
        "implementation")

    # --- Fourier-space modelling (App. A) -----------------------------------------
    psf_mode_tolerance: float = setting(
        1e-6, "Fourier modes where the PSF transform (times the brightest model) is below this fraction of its "
        "peak are dropped", "DESIGN: speed")
    mode_chi2_tolerance: float = setting(
        0.01, "Fourier modes are dropped, weakest first, while the brightest model the data allow (a point source at 3x "
        "the fitted flux plus 5 sigma) has at most this much chi^2 of its own in them in total. The data in them go "
        "too, and with them a scatter of e (0.01: rms 0.4-0.5 % of its error, at most 2.5 %, against 0 at 3.6 times "
        "the cost; it grows about as the square root of this; benchmarks/speed.py --check)", "DESIGN: speed")
    fold_chi2_tolerance: float = setting(
        0.01, "the cross terms of fold groups (modes that alias onto one sampled mode) are dropped, weakest first, "
        "while the chi^2 they could change for that brightest model stays below this in total (their own terms "
        "stay: the modes are then summed as modes alone; 0.01 moves e by at most 1.2e-5, 4e-5 of its error, "
        "benchmarks/speed.py --check)", "DESIGN: speed")
    pair_chi2_tolerance: float = setting(
        0.01, "per model, the fold groups' remaining cross terms are left out of its sums where, for that model at the "
        "brightest flux the data allow (as for mode_chi2_tolerance), they could change chi^2 by at most this (a bound "
        "from the model's own transform at their modes, far below it for most extended models; the binned sums only, "
        "benchmarks/speed.py --check); 0 keeps them in every model", "DESIGN: speed")
    mode_bins_per_octave: int = setting(
        12, "the Fourier modes of a fit are summed, per ellipticity, in bins uniform in log K^T C K, this many per "
        "factor of 2 (the model transform depends on a mode only through r^2 K^T C K; each mode is shared among four "
        "bins by cubic interpolation, so errors scale as the inverse fourth power: 12 gives the sums of every mode "
        "within 2e-6, the position's second derivatives within 1.4e-5, and moves e by at most 2.8e-6 from 16, "
        "benchmarks/README.md session 80); 0 evaluates "
        "every mode (also what the numpy path without the compiled kernel does)", "DESIGN: speed")
    mode_polar_angles: int = setting(
        80, "the modes of a fit are first spread onto a grid in log |K|^2 (a node every second bin of "
        "mode_bins_per_octave) and in the direction of K (this many nodes over 180 deg), by interpolation of six "
        "points in each; an ellipticity's bins are then made from the grid's nodes instead of every mode (their "
        "K^T C K is |K|^2 times a factor of the direction only), at a cost that does not grow with the number of "
        "modes. 80 puts the log-likelihood as close to every mode's as the bins of every mode are (1.5e-4 nats at "
        "SNR 25, benchmarks/README.md session 77). Used where it costs less than binning every mode: exposures that "
        "share a Jacobian merge their modes, and a thousand modes are binned one by one (likelihood.polar_pays). 0 bins "
        "every mode for every ellipticity", "DESIGN: speed")
    mode_polar_e_max: float = setting(
        0.95, "ellipticities up to this |e| are binned from the grid of mode_polar_angles, those above it mode by "
        "mode (a model of high |e| varies with the direction of K over an angle of order its axis ratio q; at "
        "|e| 0.95, q = 0.026, the grid's log-likelihoods are still as close to every mode's as at |e| 0.3, "
        "benchmarks/README.md session 77)", "DESIGN: speed")
    alias_correction: str = setting(
        "moffat",
        "high frequencies of a native-sampled PSF: 'moffat' models them with a circular Moffat fitted to the PSF "
        "(the paper's App. A correction), scaled mode by mode so that its aliased sum is the sampled PSF; 'none' "
        "assumes a band-limited PSF",
        "App. A", ("moffat", "none"))
    alias_oversampling: int = setting(3, "sub-sampling of the galaxy model before the alias fold", "App. A")

    # --- ellipticity sampling (sec. 3.3) ------------------------------------------
    sampling: str = setting("adaptive", "'adaptive': the paper's grid refinement; 'two-pass': find the maximum first",
                         "sec. 3.3", ("adaptive", "two-pass"))
    e_grid_start: float = setting(0.16, "starting ellipticity grid spacing", "sec. 3.3")
    e_grid_prepass: float = setting(
        0.32,
        "a coarser grid (e_grid_start times a power of 2) sampled first over the whole |e| < 1 disk: the starting "
        "grid is then sampled only within one coarse step of the coarse samples whose posterior lies less than "
        "e_grid_prepass_margin nats below the posterior cut, since the rest of it lies far below the cut, where the "
        "estimator uses nothing and the refinement never goes (0: sample the whole starting grid, the paper's)",
        "sec. 3.3 (implementation)")
    e_grid_prepass_margin: float = setting(
        10.0, "nats below the posterior cut within which a coarse pre-pass sample has the starting grid sampled "
        "around it (see e_grid_prepass)", "sec. 3.3 (implementation)")
    e_grid_min: float = setting(0.02, "finest ellipticity grid spacing", "sec. 3.3")
    n_above: int = setting(30, "samples wanted above the threshold", "sec. 3.3")
    above_fraction: float = setting(0.05, "threshold, as a fraction of the maximum posterior", "sec. 3.3")
    model_e_limit: float = setting(0.98, "largest |e| a model may have", "sec. 3.3")

    # --- estimator and weight (sec. 3.4, 3.5) --------------------------------------
    posterior_cut: float = setting(0.01, "samples whose posterior is below this fraction of its maximum are rejected",
                                "sec. 3.4")
    self_calibration: bool = setting(
        False, "self-calibration: correct each estimate for the estimator's own bias, found by measuring, as the "
        "data were measured (same exposures, PSFs, Jacobians, weights, position and ellipticity samples), "
        "noise-free images of the fitted model (its size, bulge fraction and flux) at the estimate and min(0.05, "
        "2 sigma_e) closer to e = 0, and taking the ellipticity whose model's estimate is the data's (Newton steps: "
        "self_calibration_steps). "
        "It removes most of the over-response of small galaxies' likelihood means (benchmarks/README.md, "
        "'Self-calibration and the small galaxies'), at about 2.1 times the cost of a fit; its noise bias is its "
        "own, and shearfit measure applies a default calibration fitted with it (DEFAULT_CALIBRATION_SELFCAL) "
        "where the config names none. Not applied to metacal's versions",
        "sec. 3.4 (extension)")
    self_calibration_steps: int = setting(
        1, "Newton steps of the self-calibration's solve f(e) = e_hat (each after the first one more noise-free "
        "fit of the model, radially with the secant over the last step as the response), each damped by how well "
        "the last one contracted the residual |f(e) - e_hat| (SELFCAL_DAMPING: undamped while a step shrinks it to "
        "0.3 of the last or less, fading to no step at 0.7), so that the result moves smoothly with the pixels and "
        "an estimate the model's cannot reach (a broad likelihood near the model's limit) is not carried outwards "
        "(FitResult.selfcal_steps counts the steps taken). Once an iterate lies on the other side of the solution "
        "along |e| than an earlier one (its radial residual changed sign), the two bracket it, and each further "
        "step is a secant that lands between them, taken whole (SELFCAL_BRACKETS): a first step that overshot a "
        "solution where f flattens is no longer kept. One step leaves, for galaxies of scalelength 0.1-0.125\" "
        "at |e| 0.4-0.55, residuals of up to 0.008 that alternate in sign from step to step (the response found "
        "towards e = 0 is below the one at the solution). With self_calibration_min_response 0.25, on 700 noise-free "
        "rings of such galaxies m is -0.0046 +- 0.0012 / -0.0034 +- 0.0013 with one step and -0.0012 +- 0.0011 / "
        "-0.0003 +- 0.0013 with 4 (benchmarks/README.md, session 60)",
        "sec. 3.4 (extension)")
    self_calibration_min_response: float = setting(
        0.5, "the smallest response (radial and tangential) by which the self-calibration divides the bias it finds "
        "(the largest is 1.5): 0.5 allows at most a twofold correction. Small galaxies at high |e| respond less: "
        "for a scalelength of 0.11\" at SNR 150 the noise-free estimate's slope along |e| is 0.41 between 0.6 and "
        "0.7 and 0.13-0.19 between 0.7 and 0.8 (a broad likelihood in |e|, and the prior ends at disk_e_max), so the "
        "bound cuts 12 % of the responses of galaxies of 0.1-0.125\" and leaves their correction short: m -0.007 "
        "there without noise, -0.008 with noise and noise_bias_correction (700 rings). 0.25 cuts none of them "
        "without noise; with noise_bias_correction it leaves -0.005 +- 0.003 / -0.002 +- 0.004 with one step (700 "
        "rings; session 59) and, with self_calibration_steps 4, +0.007 +- 0.002 / -0.000 +- 0.003 over 2200 plain "
        "and rotated rings (m1 from the broad likelihoods, where the extrapolation leaves its fourth-order term), "
        "where the default leaves -0.007 / -0.011 on the 800 it was run on (benchmarks/README.md, sessions 60-61; "
        "benchmarks/selfcal_response.py). At |e| 0.7-0.8 (0.1-0.125\", SNR 100-200) 0.1 removes the noise-free bias "
        "that 0.25 leaves (-0.032 -> -0.002, 240 rings) but not the noisy one, -0.067 either way with "
        "noise_bias_correction (session 68). The default calibration tables were fitted with 0.5",
        "sec. 3.4 (extension)")
    noise_bias_correction: bool = setting(
        False, "noise-bias extrapolation: measure the object twice more, with a noise field n drawn from its "
        "weights added to and subtracted from its pixels, and subtract the bias b = (e(y + n) + e(y - n)) / 2 - "
        "e(y) from the estimate e(y). Doubling the noise variance doubles the estimator's noise bias to second "
        "order, while the antithetic pair cancels the noise's first-order effect, so 2 e(y) - (e(y + n) + "
        "e(y - n)) / 2 is free of the noise bias to second order in the noise. The fits run with every other "
        "setting as given (self_calibration included), at about 2.8 times their cost; see benchmarks/README.md, "
        "'Noise-bias extrapolation'. shearfit measure applies no simulation calibration with it where the "
        "config names none. Not applied to metacal's versions",
        "sec. 3.4 (extension)")
    noise_bias_second_amplitude: float = setting(
        0.0, "with noise_bias_correction and a value a > 0 (not 1): a second antithetic pair y +- a n (the same noise "
        "field, scaled by a) measured as well, so that the extrapolation also removes the noise bias's fourth-order "
        "term C (the mean estimate e0 + B v + C v^2 at noise variance v times the data's: the one pair leaves -2 C, "
        "two pairs none): D(t) = ((e(y + t n) + e(y - t n)) / 2 - e(y)) / t^2, C = (D(a) - D(1)) / (a^2 - 1), e0 = "
        "e(y) - D(1) + 2 C. Two more fits per object (five in all). A fit's discrete jumps enter D(a) divided by "
        "a^2, so an a below 1 amplifies them: on small galaxies at SNR 100-200 the errors on m grew 3-4 times with "
        "0.5 and 1.5-1.8 times with sqrt(2) (3 e(y) - 3 e(2) + e(3) in multiples of the data's noise variance), which "
        "over 1150 rings moved m1 by -0.007 +- 0.002, the one pair's remainder (benchmarks/README.md, session 61); "
        "sqrt(3) (8/3 e(y) - 2 e(2) + e(4) / 3) gave errors 15-21 % smaller than sqrt(2) on the same 300 rings, m the "
        "same within -0.0014 +- 0.0022 / -0.0012 +- 0.0040 (session 62). 0: the one pair",
        "sec. 3.4 (extension)")
    noise_bias_on_model: bool = setting(
        False, "with noise_bias_correction: measure the noise bias on the fit's own model instead of extrapolating "
        "it from the data: the noise-free image of the model the estimate describes (its corrected ellipticity, "
        "posterior-mean size, bulge fraction and flux, at its position, as self_calibration renders it) is "
        "measured once as it is and once each with the noise field n added and "
        "subtracted, n drawn from the weights at the data's own variance, and b = (e(m + n) + e(m - n)) / 2 - e(m) "
        "is subtracted from the estimate. Each of the three is a full fit with every other setting as given. The "
        "bias is found at the data's noise level, not extrapolated to it from twice and four times the variance, so "
        "it holds where the noise bias is not a low polynomial in the variance (galaxies near the prior's end in "
        "|e|, whose bias is set up below the data's noise and then levels off); it is found at the fitted model "
        "rather than at the truth, which the data stand for in the extrapolation. Three fits per object instead of "
        "the extrapolation's two or four; noise_bias_second_amplitude is not used. On 1440 plain rings of "
        "0.1-0.125\" galaxies at SNR 100-200 (disk_e_max 0.95, 4 self-calibration steps, the same galaxies and "
        "noise) its errors on m have half the variance of the two-pair extrapolation's (sqrt(3)) at 0.82 of its "
        "cost, but m is higher by +0.0034 +- 0.0010 / +0.0024 +- 0.0014 (+0.0017 +- 0.0015 / +0.0019 +- 0.0019 "
        "against -0.0017 +- 0.0020 / -0.0005 +- 0.0027), all of it from galaxies of |e| >= 0.3, whose "
        "fitted models carry less noise bias than the galaxies (at |e| 0.3-0.5, 0.035 of m against 0.048; "
        "benchmarks/README.md, session 73)",
        "sec. 3.4 (extension)")
    corrected_e_limit: float = setting(
        0.98, "largest |e| of an estimate that self_calibration or noise_bias_correction corrected (taken as at least "
        "model_e_limit, the largest |e| of a model, within which the self-calibration's noise-free fits stay). Above "
        "model_e_limit, a solve whose solution lies beyond the models goes on from the limit along f's last secant "
        "(damped as its other steps) instead of stopping on it, and the noise-bias extrapolation is not cut there "
        "either. With noise, 18 % of the corrected estimates of 0.1-0.125\" galaxies at |e| 0.7-0.8 (SNR 100-200) stop "
        "on the limit, and that is part of their bias: 3 takes their m1 from -0.078 +- 0.010 to -0.046 +- 0.017 "
        "(480 rings, paired +0.031 +- 0.014). The estimates are then heavier-tailed: on such galaxies drawn from the "
        "prior the errors on m grow by 15-62 % and m moves by -0.004 +- 0.004 (480 rings; benchmarks/README.md, "
        "session 69). Estimates of |e| >= 1 occur (1.2 % of those, 11 % of the tail's); they are terms of an unbiased "
        "mean, not shapes",
        "sec. 3.4 (extension)")
    weight_e_max: float = setting(0.804, "e_max of the weight", "eq. (weight)")
    sigma_pop: float = setting(0.255, "1D rms ellipticity of the population, sigma_pop", "eq. (weight)")

    # --- star / galaxy (sec. 3.2) -----------------------------------------------------
    star_pvalue: float = setting(
        0.01,
        "an object is a star if the F-test probability that the galaxy model's improvement over a point source "
        "arises by chance exceeds this", "sec. 3.2")
    star_psf_error: float = setting(
        0.03,
        "fractional PSF model error allowed for in the star/galaxy test: the galaxy model's chi^2 improvement "
        "over a point source is reduced by (SNR x this)^2 before the F-test, so that bright stars, which a "
        "slightly imperfect PSF model lets a tiny galaxy fit better, stay stars (the paper's magnitude-dependent "
        "limit, matched to visual classification, expressed through the PSF error it compensates)",
        "sec. 3.2 (implementation)")
    star_faint_limit: float = setting(
        23.0,
        "objects fainter than this magnitude are never classified as stars: the paper's limit is "
        "magnitude-dependent and it expects very few stars at i > 23, where a faint small galaxy and a point "
        "source cannot be told apart by the F-test", "sec. 3.2 and its footnote")

    def __post_init__(self):
        check_choices(self)
        positive = ["disk_e_max", "disk_e_a", "bulge_fraction_sigma", "size_alpha", "size_rd_over_a",
                    "truncation", "bulge_size_ratio", "delta_chi2_crit", "flux_halfwidth", "e_grid_start",
                    "e_grid_min", "weight_e_max", "sigma_pop", "position_max_step"]
        for name in positive:
            if not getattr(self, name) > 0:
                raise ShearfitValueError(f"setting {name}={getattr(self, name)!r} must be positive")
        if not 0 <= self.bulge_population_fraction <= 1:
            raise ShearfitValueError("setting bulge_population_fraction must lie in [0, 1]")
        if self.n_flux < 5 or self.n_size < 3:
            raise ShearfitValueError("settings n_flux >= 5 and n_size >= 3 are needed for the spline integrals")
        if not 0 < self.model_e_limit < 1:
            raise ShearfitValueError("setting model_e_limit must lie in (0, 1)")
        if not self.corrected_e_limit > 0:
            raise ShearfitValueError(f"setting corrected_e_limit={self.corrected_e_limit!r} must be positive")
        if self.e_grid_prepass != 0:
            ratio = self.e_grid_prepass / self.e_grid_start
            k = round(math.log2(ratio)) if ratio > 0 else -1
            if k < 1 or abs(ratio - 2 ** k) > 1e-9 * ratio:
                raise ShearfitValueError(f"setting e_grid_prepass={self.e_grid_prepass!r} must be 0 or e_grid_start "
                                         f"({self.e_grid_start!r}) times a power of 2 (2, 4, ...)")
        if not self.e_grid_prepass_margin >= 0:
            raise ShearfitValueError(f"setting e_grid_prepass_margin={self.e_grid_prepass_margin!r} must be >= 0")
        if not 0 < self.self_calibration_min_response <= 1:
            raise ShearfitValueError(f"setting self_calibration_min_response={self.self_calibration_min_response!r} "
                                     "must lie in (0, 1]")
        if not 1 <= self.self_calibration_steps <= 20:
            raise ShearfitValueError(f"setting self_calibration_steps={self.self_calibration_steps!r} must lie in "
                                     "[1, 20]")
        a = self.noise_bias_second_amplitude
        if not (a >= 0 and abs(a - 1.0) > 1e-3 and a <= 4):
            raise ShearfitValueError(f"setting noise_bias_second_amplitude={a!r} must be 0 or lie in (0, 4] away from "
                                     "1")
        if not 0 <= self.mode_bins_per_octave <= 4096:
            raise ShearfitValueError(f"setting mode_bins_per_octave={self.mode_bins_per_octave!r} must lie in [0, 4096]")
        if not (self.mode_polar_angles == 0 or 12 <= self.mode_polar_angles <= 4096):
            raise ShearfitValueError(f"setting mode_polar_angles={self.mode_polar_angles!r} must be 0 or lie in "
                                     "[12, 4096]")
        if not 0 <= self.mode_polar_e_max < 1:
            raise ShearfitValueError(f"setting mode_polar_e_max={self.mode_polar_e_max!r} must lie in [0, 1)")

    def replace(self, **changes) -> "FitConfig":
        return fit_config_from_mapping({**self.to_dict(), **changes})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def check_choices(settings) -> None:
    """Raise :class:`ShearfitValueError` (one line naming the setting) where a field of the settings dataclass
    ``settings`` declared with ``choices`` (:func:`setting`) holds another value."""
    for f in fields(settings):
        choices = f.metadata.get("choices")
        value = getattr(settings, f.name)
        if choices is not None and value not in choices:
            raise ShearfitValueError(f"setting {f.name}={value!r} is not one of {', '.join(map(repr, choices))}")


def coerce_setting(name: str, ftype, value, source: str | None = None):
    """Check a setting's value against its declared type; an int is accepted where a float is wanted (YAML
    writes 2 for 2.0) and returned as a float.

    Raises :class:`ShearfitValueError` with one line naming the setting (and ``source``, the file or
    override it came from, when given).
    """
    kind = str(ftype).replace("'", "").replace("<class ", "").replace(">", "")
    ok = {
        "bool": isinstance(value, bool),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
    }.get(kind, True)
    if not ok:
        where = f"{source}: " if source else ""
        raise ShearfitValueError(f"{where}setting {name}={value!r} must be of type {kind}")
    return float(value) if kind == "float" else value


def settings_from_items(items) -> dict:
    """Settings given as ``KEY=VALUE`` strings (the benchmarks' ``--set``) as a mapping, each value read as a
    config file reads it (YAML: 16 is an int, 0.32 a float, true a bool); an item without ``=`` is refused."""
    import yaml

    mapping = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ShearfitValueError(f"--set needs KEY=VALUE, got {item!r}")
        mapping[key.strip()] = yaml.safe_load(value)
    return mapping


def fit_config_from_mapping(mapping: Mapping[str, Any] | None) -> FitConfig:
    """Build a :class:`FitConfig` from a mapping, rejecting unknown keys and wrong types."""
    mapping = dict(mapping or {})
    known = {f.name: f for f in fields(FitConfig)}
    unknown = sorted(set(mapping) - set(known))
    if unknown:
        raise ShearfitKeyError(f"unknown setting {unknown[0]!r} (valid: {', '.join(sorted(known))})")
    kwargs = {k: coerce_setting(k, known[k].type, v) for k, v in mapping.items()}
    return FitConfig(**kwargs)


def as_config(config) -> FitConfig:
    """A :class:`FitConfig` from ``None`` (the defaults), a :class:`FitConfig` or a mapping of settings."""
    if config is None:
        return FitConfig()
    if isinstance(config, FitConfig):
        return config
    if isinstance(config, Mapping):
        return fit_config_from_mapping(config)
    raise ShearfitValueError(f"config must be a FitConfig or a mapping, got {type(config).__name__}")


def describe() -> str:
    """One line per setting: name, default, reference, help."""
    lines = []
    for f in fields(FitConfig):
        lines.append(f"{f.name} = {f.default!r}  [{f.metadata.get('ref', '')}]  {f.metadata.get('help', '')}")
    return "\n".join(lines)
