#!/usr/bin/env python
"""Ring test of shearfit against GalSim-simulated galaxies: multiplicative and additive bias.

Every galaxy of the paper's population (priors.sample_population) is simulated
by GalSim on several dithered exposures with elliptical Moffat PSFs, at
``--n-rotations`` orientations (a ring), once with shear +g and once with -g.
The two runs share galaxy, PSFs, dithers *and noise*, so in

    m_i = (<e_i>_+ - <e_i>_-) / (2 g_i) - 1,     c_i = (<e_i>_+ + <e_i>_-) / 2

(``<>`` the weighted mean over all objects of a sign) most of the shape noise
and of the pixel noise cancel. Errors come from a bootstrap over galaxies (a
galaxy carries its whole +g/-g ring pair). With a wide SNR range, m is also
printed in SNR bins: that is the noise bias the calibration has to remove.

Examples
--------
Smoke test (seconds)::

    python benchmarks/ring_test.py --n-galaxies 8

Simulation only, while the engine is unavailable::

    python benchmarks/ring_test.py --n-galaxies 8 --dry-run

Noise bias across SNR::

    python benchmarks/ring_test.py --n-galaxies 2000 --snr-min 10 --snr-max 100 --out ring.fits

Metacalibration (issue 8): every object measured in its five metacal versions; the shear of each sign
is <R>^-1 <e> with the ensemble response (shear and selection, :mod:`shearfit.calib.metacal`), no external
calibration. The symmetrising noise of an object is the same at +g and -g, so it cancels too::

    python benchmarks/ring_test.py --n-galaxies 400 --snr-min 10 --snr-max 40 --metacal

Runs of several seeds add up (``--out`` each, then ``--from-tables``), and a simulation calibration
made from other tables (the paper's population, say) is applied to them with ``--reference-tables``::

    python benchmarks/ring_test.py --from-tables odd_s*.fits --reference-tables paper_s*.fits \
        --snr-min 10 --snr-max 40

Two runs on the same galaxies and noise that differ by a setting (``--set``) compare object by object, with
the m and c differences' errors from the same galaxies resampled for both (much smaller than either's own)::

    python benchmarks/ring_test.py --from-tables A.fits --paired-with B.fits --snr-min 20 --snr-max 40 --seed 11

``--antithetic`` also measures each object's antithetic twin (minus the noise): the terms odd in the
noise cancel within a ring, which shrinks the errors on c several times; on m the twins gain less
(the noise of the metacal response is largely even in the noise).

``--with-plain`` (with --metacal) also fits every object with plain lensfit, and ``--from-tables ...
--plain`` reports those fits, so one run gives both sides of a comparison of metacal with the
simulation calibration.

With ``--out T``, the galaxies measured so far are written to ``T``'s checkpoint (``T.partial.fits`` for
``T.fits``) about once a minute, and removed when ``T`` is written. A run that was stopped continues with the
same command and ``--resume``: the galaxies in the checkpoint are kept and only the others are measured (every
galaxy's draws come from its own seed, so the final table is the uninterrupted run's)::

    python benchmarks/ring_test.py --n-galaxies 800 --metacal --antithetic --seed 87 --out T.fits --resume

A metacal run's result can be kept without its per-object tables (several MB per 800 galaxies): ``--save-sums``
writes, per galaxy and sign, the weighted sums its metacal m and c are made of (about 180 bytes per galaxy;
:func:`shearfit.calib.bias.metacal_ring_sums`), and ``--from-tables`` reads such files beside tables. The
metacal report and lensfit's m on the noshear images come out as from the tables (the bootstrap resamples the
same galaxies); the reports that need the objects (other weights, --all-objects) do not::

    python benchmarks/ring_test.py --from-tables T.fits --metacal --snr-min 10 --snr-max 40 --save-sums S.fits
    python benchmarks/ring_test.py --from-tables benchmarks/campaigns/outside_metacal/*.fits --metacal \
        --snr-min 10 --snr-max 40

Galaxy sums of two settings pair galaxy by galaxy (``--paired-with``): each galaxy of ``--from-tables`` is found
among the other's by its family, half-light radius and target SNR, drawn from its own seed. The other side may be
a longer campaign: then the first setting's m on the other's whole population is also given, as the other's m
there plus the paired difference (a control variate: the paired difference is better measured than either m,
so a short campaign of a new setting borrows some of the precision of a long one)::

    python benchmarks/ring_test.py --from-tables benchmarks/campaigns/own_grid_metacal/*.fits --metacal \
        --snr-min 10 --snr-max 40 --paired-with benchmarks/campaigns/outside_metacal/*.fits

A setting that changes only the faint galaxies' estimates is run on them alone (``--measure-snr-below 20``: every
galaxy is drawn, only those below SNR 20 are measured) and read with ``--paired-below 20``: the other campaign's
population with its galaxies below that SNR moved to the new setting (the summed move of those measured scaled up to
all of them, within each size bin with ``--hlr-log-uniform``) and the others kept as they were::

    python benchmarks/ring_test.py --from-tables benchmarks/campaigns/stepcap_outside/faint/*.fits --metacal \
        --snr-min 10 --snr-max 40 --paired-with benchmarks/campaigns/outside_metacal/*.fits --paired-below 20
"""

from __future__ import annotations

import os

# One BLAS / FFT thread per worker: the pool provides the parallelism, and the throughput is
# quoted per process. Must be set before numpy is imported.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from multiprocessing import Pool  # noqa: E402

import numpy as np  # noqa: E402

import shearfit  # noqa: E402
from shearfit.simulate import ring_set  # noqa: E402
from shearfit.simulate.field import truth_galaxies  # noqa: E402
from shearfit.simulate.outside import outside_population, outside_profile  # noqa: E402
from shearfit.simulate.stamps import NegatedNormal  # noqa: E402
from shearfit.calib.bias import (METACAL_SUM_NAMES, bias_from_sums, bootstrap_counts, format_with_error,  # noqa: E402
                                  galaxy_column, metacal_bias_from_sums, metacal_ring_sums, paired_weights, ring_sums,
                                  shear_bias, shear_bias_by_snr, snr_bin_masks)
from shearfit.calib.weights import isotropic_weights  # noqa: E402
from shearfit.config import FitConfig  # noqa: E402
from shearfit.engine.sampling import lensing_weight  # noqa: E402

# m(SNR) is printed when snr_max / snr_min exceeds this: a narrower range has no noise-bias trend to see.
WIDE_SNR_RATIO = 2.5
#: the shear of the +g objects of a run without --shear
DEFAULT_SHEAR = (0.03, -0.02)
#: runs needed for the jackknife over runs of --from-tables (report_runs_jackknife)
JACKKNIFE_MIN_RUNS = 5
#: bins in ln(half-light radius) of --hlr-log-uniform's weights
HLR_WEIGHT_BINS = 20
RESULT_FIELDS = ("e1", "e2", "e_var", "weight", "snr", "scalelength", "bulge_fraction", "model_flux", "flux_snr",
                 "round_scalelength")
#: with self_calibration (not metacal): the correction subtracted from the likelihood mean, the responses found
#: on the model (radial, tangential) and the Newton steps kept (FitResult.selfcal_de, selfcal_response,
#: selfcal_steps; tables from session 59 on)
SELFCAL_FIELDS = ("sc_de1", "sc_de2", "sc_rrad", "sc_rtan", "sc_steps")
#: fields that tables written before session 57 have not
NEWER_FIELDS = ("flux_snr", "round_scalelength")
METACAL_FIELDS = tuple(f"{q}_{v}" for v in ("1p", "1m", "2p", "2m") for q in ("e1", "e2", "weight", "fitclass")) + \
    ("R11", "R12", "R21", "R22")


# ----------------------------------------------------------------------------- workers

def _galaxies_for(errors, root, target):
    """How many galaxies bring the larger of ``errors`` (over ``root**2`` galaxies) to ``target``; "?" where
    an error is not finite (a subset too small to resample)."""
    worst = float(np.max(errors)) * root
    return int(np.ceil((worst / target) ** 2)) if np.isfinite(worst) else "?"


def psf_fwhm_of(obs):
    """Mean PSF FWHM (arcsec) over an object's exposures, as ``shearfit measure`` writes its ``psf_fwhm``."""
    from shearfit.pipeline.driver import psf_fwhm_arcsec, psf_moments

    with np.errstate(all="ignore"):
        return float(np.nanmean([psf_fwhm_arcsec(o.jacobian, o.psf_oversampling, psf_moments(o.psf)) for o in obs]))


def _work(task):
    """Simulate one galaxy's +g and -g rings and (unless dry) measure every object.

    Runs in a pool worker; everything it needs arrives in ``task`` so that it
    is independent of the start method.
    """
    index, seed, opts = task
    g = np.array(opts["shear"], dtype=float)
    measure = None if opts["dry_run"] else _get_measure_object()
    cfg = opts["config"]
    records = []
    t_sim = t_meas = 0.0
    metacal = opts.get("metacal", False)
    n_rot = opts["ring_kwargs"]["n_rotations"]
    draw_cache = {}   # what the two signs share: PSF images and transforms, the unsheared stamps
    if metacal:
        from shearfit.calib import metacal as metacal_module

        metacal_module.SYMMETRISE_NOISE = not opts.get("metacal_unsymmetrised", False)
    for sign in (+1, -1):
        # The same seed for both signs: nothing ring_set draws depends on the shear, so the
        # galaxy, PSFs, dithers and noise are identical and cancel in the +g / -g difference.
        # The antithetic twin (noise_sign -1) has the same galaxies and stamps and minus the noise (drawn
        # with them, in one call); the twins are measured after the first members, as when each had its own call
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        rings = ring_set(1, tuple(sign * g), rng, cfg=opts.get("population_config", cfg),
                         antithetic=bool(opts.get("antithetic")), draw_cache=draw_cache, **opts["ring_kwargs"])
        t_sim += time.perf_counter() - t0
        below = opts.get("measure_snr_below")
        if below is not None and not rings[0][1]["snr"] < below:
            return [], t_sim, t_meas   # drawn, not measured (every galaxy has its own seed: the others are unchanged)
        rings = [r for r in rings if r[1]["noise_sign"] > 0] + [r for r in rings if r[1]["noise_sign"] < 0]
        for obs, truth in rings:
            noise_sign = truth["noise_sign"]
            rec = {
                "galaxy": index, "sign": sign,
                # the twin's objects are more members of the same ring (rotation numbers after the first's)
                "rotation": truth["rotation"] + (n_rot if noise_sign < 0 else 0),
                "g1": truth["g1"], "g2": truth["g2"], "e1_int": truth["e1_int"], "e2_int": truth["e2_int"],
                "true_scalelength": truth["scalelength"], "true_bulge_fraction": truth["bulge_fraction"],
                "is_bulge": truth["is_bulge"], "mag": truth["mag"], "flux": truth["flux"],
                "snr_target": truth["snr"], "snr_true": truth["snr_true"], "sigma": truth["sigma"],
                "psf_fwhm_mean": float(np.mean(truth["psf_fwhm"])), "psf_beta_mean": float(np.mean(truth["psf_beta"])),
                # the PSF size as shearfit measure's catalogue gives it (its psf_fwhm column): what a calibration
                # table of size: resolution takes the scalelength relative to
                "psf_fwhm": psf_fwhm_of(obs),
                "psf_e1_mean": float(np.mean(truth["psf_e1"])), "psf_e2_mean": float(np.mean(truth["psf_e2"])),
                "n_redraws": truth["n_redraws"],
                "peak_over_sigma": float(max(o.image.max() for o in obs) / truth["sigma"]),
                # galaxies outside the model family (--population outside): the family and half-light radius
                "family": int(truth["fields"].get("family", -1)), "true_hlr": float(truth["fields"].get("hlr", np.nan)),
                "fitclass": -99, "time": np.nan, "error": "",
            }
            for name in RESULT_FIELDS + (METACAL_FIELDS if metacal else ()):
                rec[name] = np.nan
            if cfg.noise_bias_correction:
                rec["nb_de1"] = rec["nb_de2"] = np.nan
                if cfg.noise_bias_second_amplitude > 0:
                    rec["nb1_de1"] = rec["nb1_de2"] = np.nan
            if cfg.self_calibration and not metacal:
                for name in SELFCAL_FIELDS:
                    rec[name] = np.nan
            if measure is not None and metacal:
                from shearfit.calib.metacal import SHEARED, measure_metacal

                t0 = time.perf_counter()
                mrng = np.random.default_rng([int(seed.generate_state(1)[0]), truth["rotation"]])
                if noise_sign < 0:   # the twin's symmetrising noise is minus the first's too
                    mrng = NegatedNormal(mrng)
                mc = measure_metacal(obs, truth["mag"], cfg, rng=mrng, psf=opts.get("metacal_psf", "dilated"),
                                     replay=not opts.get("metacal_fresh", False),
                                     own_position=opts.get("metacal_own_position", False),
                                     own_samples=opts.get("metacal_own_samples", False),
                                     own_sizes=opts.get("metacal_own_sizes", False))
                res = mc.noshear
                rec["fitclass"] = int(res.fitclass)
                for name in RESULT_FIELDS:
                    rec[name] = float(getattr(res, name, np.nan))
                for v in SHEARED:
                    for q in ("e1", "e2", "weight", "fitclass"):
                        rec[f"{q}_{v}"] = float(getattr(mc.results[v], q))
                for i in range(2):
                    for j in range(2):
                        rec[f"R{i + 1}{j + 1}"] = float(mc.R[i, j])
                rec["time"] = time.perf_counter() - t0
                t_meas += rec["time"]
                if opts.get("with_plain"):
                    # plain lensfit on the same stamps (the simulation calibration's side of issue 8's item 2)
                    res = measure(obs, mag=truth["mag"], config=cfg)
                    rec["plain_fitclass"] = int(res.fitclass)
                    for name in RESULT_FIELDS:
                        rec[f"plain_{name}"] = float(getattr(res, name, np.nan))
            elif measure is not None:
                t0 = time.perf_counter()
                # the noise that noise_bias_correction adds: the same at +g and -g, as the pixel noise is
                kw = {"noise_seed": [int(seed.generate_state(1)[0]), truth["rotation"], int(noise_sign > 0)]} \
                    if cfg.noise_bias_correction else {}
                try:
                    res = measure(obs, mag=truth["mag"], config=cfg, **kw)
                except Exception as exc:  # a benchmark reports failures, it does not stop on them
                    rec["fitclass"] = -2
                    rec["error"] = f"{type(exc).__name__}: {exc}"[:200]
                else:
                    rec["fitclass"] = int(res.fitclass)
                    for name in RESULT_FIELDS:
                        rec[name] = float(getattr(res, name, np.nan))
                    if res.noise_bias_de is not None:
                        rec["nb_de1"], rec["nb_de2"] = res.noise_bias_de
                        if cfg.noise_bias_second_amplitude > 0:
                            rec["nb1_de1"], rec["nb1_de2"] = res.noise_bias_de_one_pair
                    if cfg.self_calibration and res.selfcal_de is not None:
                        rec["sc_de1"], rec["sc_de2"] = res.selfcal_de
                        rec["sc_rrad"], rec["sc_rtan"] = res.selfcal_response
                        rec["sc_steps"] = float(res.selfcal_steps)
                rec["time"] = time.perf_counter() - t0
                t_meas += rec["time"]
            records.append(rec)
    return records, t_sim, t_meas


def _get_measure_object():
    measure = getattr(shearfit, "measure_object", None)
    if measure is None:
        raise RuntimeError("shearfit.measure_object is not available in this version; run with --dry-run "
                           "to test the simulation alone")
    return measure


def _paper_population(mags, rng, cfg):
    """The paper's population (the priors' draws) as a dict of writable arrays, for the variants below."""
    from shearfit.engine.priors import sample_population

    rec = sample_population(mags, rng, cfg)
    return {k: np.array(rec[k], copy=True) for k in rec.dtype.names}


def odd_population(mags, rng, cfg):
    """A population unlike the priors (issue 8): sizes doubled, a third of the galaxies single Sersic n = 2.5
    profiles, ellipticities Gaussian with an rms |e| of 0.3 (redrawn above 0.9)."""
    pop = _paper_population(mags, rng, cfg)
    n = len(mags)
    pop["scalelength"] = 2.0 * np.asarray(pop["scalelength"], float)
    e = rng.normal(0.0, 0.3 / np.sqrt(2.0), (n, 2))
    for _ in range(100):
        big = np.hypot(e[:, 0], e[:, 1]) >= 0.9
        if not big.any():
            break
        e[big] = rng.normal(0.0, 0.3 / np.sqrt(2.0), (int(big.sum()), 2))
    pop["e1"], pop["e2"] = e[:, 0], e[:, 1]
    pop["sersic_n"] = np.where(rng.uniform(size=n) < 1.0 / 3.0, 2.5, np.nan)
    return pop


def sized_population(mags, rng, cfg, size_range):
    """The paper's population with scalelengths log-uniform over ``size_range`` (arcsec) instead of the size
    prior's: many rings of one range of sizes (the small galaxies), each drawn after the rest of the galaxy."""
    pop = _paper_population(mags, rng, cfg)
    lo, hi = np.log(size_range[0]), np.log(size_range[1])
    pop["scalelength"] = np.exp(rng.uniform(lo, hi, len(mags)))
    return pop


def e_ranged_population(mags, rng, cfg, base, e_range):
    """``base``'s galaxies (the paper's population where None) with intrinsic |e| drawn uniformly over ``e_range``
    after the rest of the galaxy, their position angles kept: rings of one range of ellipticities (the high-|e|
    tail)."""
    pop = (base or _paper_population)(mags, rng, cfg)
    phi = np.arctan2(np.asarray(pop["e2"], float), np.asarray(pop["e1"], float))
    a = rng.uniform(e_range[0], e_range[1], len(mags))
    pop["e1"], pop["e2"] = a * np.cos(phi), a * np.sin(phi)
    return pop


def replayed_population(mags, rng, cfg, galaxies):
    """The galaxies of simulated fields (:func:`shearfit.simulate.field.truth_galaxies`), one drawn at random
    with its magnitude (so in the fields' proportions): a ring of a field's galaxy, to compare rings and fields
    on the same galaxies."""
    pop = _paper_population(mags, rng, cfg)
    k = rng.integers(0, galaxies["mag"].size, len(mags))
    for name in ("mag", "scalelength", "bulge_fraction", "is_bulge", "e1", "e2"):
        pop[name] = galaxies[name][k].astype(pop[name].dtype)
    return pop


# ----------------------------------------------------------------------------- reports

def report_bias(tab, args, n_gal):
    g = np.array(args.shear, dtype=float)
    rng = np.random.default_rng([args.seed, 12345])
    weighted = not args.unweighted
    sums = ring_sums(tab, n_gal, weighted)
    est, err = shear_bias(sums, g, args.n_bootstrap, rng)
    fail = tab["fitclass"] != 0
    print(f"\nshear bias ({'weighted' if weighted else 'unweighted'} means, {args.n_bootstrap} bootstrap "
          f"resamplings of {n_gal} galaxies):")
    print(f"  m1 = {format_with_error(est[0], err[0])}    c1 = {format_with_error(est[2], err[2])}")
    print(f"  m2 = {format_with_error(est[1], err[1])}    c2 = {format_with_error(est[3], err[3])}")
    print_leakage(est[2:4], err[2:4], args)
    # the same rings with weights that do not respond to the shear: each +g / -g pair's mean weight (ring
    # tables), and the mean of each bin of flux_snr (what a catalogue can use: its iso_weight; tables written
    # before session 57 have no flux_snr)
    others = []
    if weighted and "rotation" in tab.dtype.names:
        others.append(("each pair's mean weight (no weight responds to the shear)", paired_weights))
    if weighted and "flux_snr" in tab.dtype.names and "round_scalelength" in tab.dtype.names:
        others.append(("isotropic weights (each the mean of its bin of flux_snr, as iso_weight)",
                       isotropic_weights))
    for label, weights_of in others:
        alt = tab.copy()
        alt["weight"] = weights_of(tab)
        ae, aerr = shear_bias(ring_sums(alt, n_gal), g, args.n_bootstrap, np.random.default_rng([args.seed, 12345]))
        print(f"  with {label}: m1 = {format_with_error(ae[0], aerr[0])}, m2 = {format_with_error(ae[1], aerr[1])}")
    # the simulation calibration of the paper (or a calibration file): m(nu, r) of the measured galaxies
    from shearfit.calib.calibrate import PAPER_ALPHA, PAPER_BETA, as_model

    model = as_model(args.calibration if args.calibration else (PAPER_ALPHA, PAPER_BETA))
    good = tab["fitclass"] == 0
    if (model.size == "resolution" or model.seeing) and "psf_fwhm" not in tab.dtype.names:
        print(f"  (the calibration {args.calibration} needs psf_fwhm, which these ring tables lack)")
        return
    mc = model.m_of(tab)
    w = np.where(good & np.isfinite(mc), np.nan_to_num(tab["weight"]) if weighted else 1.0, 0.0)
    mbar = float(np.sum(w * np.nan_to_num(mc)) / np.sum(w))
    cal = (1 + est[:2]) / (1 + mbar) - 1
    what = (f"the {model.kind} calibration of {args.calibration}" if args.calibration else
            f"the paper's m(nu, r), (alpha, beta) = ({PAPER_ALPHA}, {PAPER_BETA})")
    print(f"  calibrated with {what}: <m> = {mbar:+.4f}, "
          f"m1 = {format_with_error(cal[0], err[0] / (1 + mbar))}, m2 = {format_with_error(cal[1], err[1] / (1 + mbar))}")
    print(f"  fitclass != 0: {fail.mean():.3%} of {len(tab)} objects"
          + "".join(f"; {int((tab['fitclass'] == k).sum())} x fitclass {k}" for k in np.unique(tab["fitclass"])
                    if k != 0))
    errs = [e for e in tab["error"] if e] if "error" in tab.dtype.names else []   # (a field's table has none)
    if errs:
        print(f"  {len(errs)} objects raised; first: {errs[0]}")
    good = ~fail
    if good.any():
        target = f"{np.mean(tab['snr_target']):.1f}" if "snr_target" in tab.dtype.names else "none"
        print(f"  mean SNR measured {np.nanmean(tab['snr'][good]):.1f} (target {target}); "
              f"sum of weights {np.nansum(tab['weight'][good]):.4g}; mean weight {np.nanmean(tab['weight'][good]):.4g}")
        if weighted and not np.nansum(tab["weight"][good]) > 0:
            print("  all weights are zero: rerun with --unweighted to see the unweighted bias")
    # m against SNR: the noise-bias signature the calibration removes (sec. 8.4).
    if args.snr_max / args.snr_min > WIDE_SNR_RATIO and args.snr_bins > 1:
        edges = np.geomspace(args.snr_min, args.snr_max, args.snr_bins + 1)
        bins = shear_bias_by_snr(sums, galaxy_column(tab, "snr_target", n_gal), edges, g, args.n_bootstrap, rng)
        print("\n  m against target SNR (bootstrap errors):")
        print("      SNR range     n_gal   <SNR meas>            m1                     m2")
        for b in bins:
            if b["n_galaxies"] < 2:
                continue
            e_b, err_b = b["estimate"], b["errors"]
            rows = np.isin(tab["galaxy"], b["galaxies"]) & good
            snr_b = np.nanmean(tab["snr"][rows]) if rows.any() else np.nan
            print(f"    {b['lo']:6.1f} - {b['hi']:6.1f}  {b['n_galaxies']:6d}   {snr_b:9.1f}   "
                  f"{format_with_error(e_b[0], err_b[0])}   {format_with_error(e_b[1], err_b[1])}")


def print_leakage(c, err, args):
    """With --psf-e-fixed: the PSF leakage alpha = c_i / e_psf,i of each component whose PSF ellipticity is not 0."""
    e_psf = getattr(args, "psf_e_fixed", None)
    if not e_psf:
        return
    parts = [f"alpha{i + 1} = c{i + 1} / {e:+g} = {format_with_error(c[i] / e, err[i] / abs(e))}"
             for i, e in enumerate(e_psf) if e != 0]
    if parts:
        print(f"  PSF leakage (every exposure's PSF ellipticity ({e_psf[0]:+g}, {e_psf[1]:+g})): " + ", ".join(parts))


class MetacalRings:
    """A metacal ring run reduced to its galaxies: per galaxy and sign the sums its m and c are made of
    (:func:`shearfit.calib.bias.metacal_ring_sums`), with the galaxy's family, half-light radius, target SNR and
    object counts. A long run's result kept in about 180 bytes per galaxy (``--save-sums``), and reported again
    with ``--from-tables``, alone or with other runs' tables."""

    #: header keyword that marks a file of galaxy sums (its value: the version of the layout)
    KEYWORD = "RINGSUMS"

    def __init__(self, sums, family, true_hlr, snr_target, n_objects, n_other, g, weighted):
        self.sums = np.asarray(sums, dtype=np.float64)
        self.family = np.asarray(family, dtype=int)
        self.true_hlr = np.asarray(true_hlr, dtype=float)
        self.snr_target = np.asarray(snr_target, dtype=float)
        self.n_objects = np.asarray(n_objects, dtype=int)
        self.n_other = np.asarray(n_other, dtype=int)
        self.g = tuple(float(x) for x in g)
        self.weighted = bool(weighted)

    @property
    def n_galaxies(self):
        return self.sums.shape[1]

    @classmethod
    def from_table(cls, tab, n_gal, args):
        gal = np.asarray(tab["galaxy"])

        def per_galaxy(name, default):
            return (galaxy_column(tab, name, n_gal) if name in tab.dtype.names else np.full(n_gal, default))

        count = np.bincount(gal, minlength=n_gal)
        other = np.bincount(gal, weights=np.asarray(tab["fitclass"]) != 0, minlength=n_gal)
        family = np.nan_to_num(per_galaxy("family", -1), nan=-1)
        all_objects = args.all_objects
        return cls(metacal_ring_sums(tab, n_gal, weighted=not (args.unweighted or all_objects), select=not all_objects),
                   family, per_galaxy("true_hlr", np.nan),
                   per_galaxy("snr_target", np.nan), count, other, args.shear, not (args.unweighted or all_objects))

    def weighted_by(self, w):
        """The same galaxies, each one's sums times its sampling weight ``w`` (all the sums are linear in the
        objects' weights, so this is the estimator on a population in which galaxy i counts ``w[i]`` times)."""
        return MetacalRings(self.sums * np.asarray(w, dtype=float)[None, :, None], self.family, self.true_hlr,
                            self.snr_target, self.n_objects, self.n_other, self.g, self.weighted)

    def subset(self, sel):
        sel = np.asarray(sel)
        return MetacalRings(self.sums[:, sel], self.family[sel], self.true_hlr[sel], self.snr_target[sel],
                            self.n_objects[sel], self.n_other[sel], self.g, self.weighted)

    @classmethod
    def concatenate(cls, parts, source=""):
        first = parts[0]
        for p in parts[1:]:
            if not np.allclose(p.g, first.g) or p.weighted != first.weighted:
                raise ValueError(f"{source}: runs of another shear or weighting (g = {p.g}, weighted {p.weighted}; "
                                 f"the first's {first.g}, {first.weighted}) do not add up")
        cat = [np.concatenate([getattr(p, k) for p in parts], axis=1 if k == "sums" else 0)
               for k in ("sums", "family", "true_hlr", "snr_target", "n_objects", "n_other")]
        return cls(*cat, first.g, first.weighted)

    def write(self, path, sources=()):
        from astropy.table import Table

        t = Table({"family": self.family.astype(np.int16), "true_hlr": self.true_hlr.astype(np.float32),
                   "snr_target": self.snr_target.astype(np.float32), "n_objects": self.n_objects.astype(np.int16),
                   "n_other": self.n_other.astype(np.int16),
                   # float32: a galaxy's sums of e differ between its signs by ~2g of their size, 1e5 times
                   # float32's resolution
                   "sums": np.moveaxis(self.sums, 1, 0).astype(np.float32)})
        t.meta[self.KEYWORD] = 1
        t.meta["G1"], t.meta["G2"] = self.g
        t.meta["WEIGHTED"] = self.weighted
        t.meta["SUMNAMES"] = ",".join(n.replace(" ", "*") for n in METACAL_SUM_NAMES)
        t.meta["COMMENTS"] = [f"galaxy sums of the ring tables {os.path.basename(s)}" for s in sources]
        _write_table(t.as_array(), path, meta=t.meta)

    @classmethod
    def read(cls, path):
        from astropy.table import Table

        t = Table.read(path)
        if cls.KEYWORD not in t.meta:
            raise ValueError(f"{path}: not a file of galaxy sums (no header {cls.KEYWORD})")
        names = t.meta.get("SUMNAMES", "").replace("*", " ").split(",")
        if tuple(names) != METACAL_SUM_NAMES:
            raise ValueError(f"{path}: header SUMNAMES lists other sums than this program's")
        sums = np.moveaxis(np.asarray(t["sums"], dtype=np.float64), 0, 1)
        return cls(sums, t["family"], t["true_hlr"], t["snr_target"], t["n_objects"], t["n_other"],
                   (t.meta["G1"], t.meta["G2"]), t.meta["WEIGHTED"])

    def keys(self):
        """Each galaxy's (family, half-light radius, target SNR) as float32 (as a file of sums keeps them): drawn
        from the galaxy's own seed, the same for a galaxy in every run of its seed, whatever the setting. The paper's
        population has no half-light radius (NaN, which equals nothing): it keys as -1."""
        hlr = np.nan_to_num(self.true_hlr.astype(np.float32), nan=-1.0)
        return list(zip(self.family.tolist(), hlr.tolist(),
                        self.snr_target.astype(np.float32).tolist()))

    def match_in(self, other, source=""):
        """Indices into ``other`` (a run of another setting holding these galaxies, and maybe more) of each of
        these galaxies, found by :meth:`keys`. Raises ValueError if a galaxy is missing there. Galaxies whose keys
        coincide (the paper's population keys by its target SNR alone, and float32 holds a few million values in
        10-14: some 4 coincidences among 6000 galaxies) pair in their order of occurrence, which is the same on
        both sides where the runs of the same seeds come in the same order (a different order pairs those few
        galaxies with others of the same SNR, which only weakens the pairing)."""
        where = {}
        for i, k in enumerate(other.keys()):
            where.setdefault(k, []).append(i)
        queues = {k: iter(v) for k, v in where.items()}
        idx = np.array([next(queues.get(k, iter(())), -1) for k in self.keys()], dtype=int)
        if np.any(idx < 0):
            raise ValueError(f"{source}: {int(np.sum(idx < 0))} of the {idx.size} galaxies of --from-tables are not "
                             "among its galaxies (give the other setting's runs of the same seeds)")
        return idx

    @classmethod
    def is_sums_file(cls, path):
        from astropy.io import fits

        try:
            with fits.open(path) as hdul:
                return len(hdul) > 1 and cls.KEYWORD in hdul[1].header
        except OSError:
            return False


def hlr_bins(hlr, lo, hi, n_bins=HLR_WEIGHT_BINS):
    """Each half-light radius's bin of ``n_bins`` equal bins of ln(hlr) over [lo, hi]: (bin, inside, edges)."""
    x = np.log(np.asarray(hlr, dtype=float))
    edges = np.linspace(np.log(lo), np.log(hi), n_bins + 1)
    inside = np.isfinite(x) & (x >= edges[0]) & (x <= edges[-1])
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_bins - 1), inside, edges


def hlr_log_uniform_weights(hlr, lo, hi, n_bins=HLR_WEIGHT_BINS):
    """Weights that make galaxies drawn from runs of different size ranges one population with half-light
    radii log-uniform from ``lo`` to ``hi``: each galaxy's weight is the inverse of the number of galaxies in its
    bin of ln(hlr) (``n_bins`` equal bins), scaled to a mean of one; galaxies outside [lo, hi] weigh 0.

    Runs of the outside population in 64-pixel stamps hold half-light radii up to about 0.9" (larger galaxies
    are redrawn), so the population of 0.1-2" is a run in 64-pixel stamps joined with one of the large galaxies
    in 128-pixel ones (``--size-range``), each galaxy weighted by how thinly its size was sampled."""
    k, inside, edges = hlr_bins(hlr, lo, hi, n_bins)
    count = np.bincount(k[inside], minlength=n_bins)
    if np.any(count == 0):
        raise ValueError(f"--hlr-log-uniform {lo:g} {hi:g}: no galaxy of half-light radius "
                         f"{np.exp(edges[np.argmin(count)]):.3g}-{np.exp(edges[np.argmin(count) + 1]):.3g}\" in "
                         "the runs given, so their sizes cannot be made log-uniform over that range")
    w = np.where(inside, 1.0 / count[k], 0.0)
    return w * (inside.sum() / w.sum())


def _metacal_check(rings, args):
    if not np.allclose(rings.g, args.shear) or rings.weighted == bool(args.unweighted):
        raise ValueError(f"galaxy sums of g = {rings.g}, {'lensfit' if rings.weighted else 'unit'} weights: give "
                         "the --shear and --unweighted of the runs")


def table_shear(tab, default):
    """The shear (g1, g2) of a ring table's +g objects (its ``g1``, ``g2`` and ``sign`` columns), else ``default``."""
    names = tab.dtype.names if hasattr(tab, "dtype") else tab.colnames
    if not {"g1", "g2", "sign"} <= set(names):
        return None if default is None else tuple(default)
    plus = np.asarray(tab["sign"]) > 0
    if not np.any(plus):
        return None if default is None else tuple(default)
    return float(np.asarray(tab["g1"])[plus][0]), float(np.asarray(tab["g2"])[plus][0])


def resolve_shear(args, found):
    """Set ``args.shear`` to the shear of the runs read (``found``: (source, shear or None) each): given, every
    run's must be it; else the first run's, and every other's must equal that. A table's g would otherwise be
    taken for the default's (a run at another shear then reads as a biased one)."""
    for source, g in found:
        if g is None:
            continue
        if args.shear is None:
            args.shear = [float(g[0]), float(g[1])]
        elif not np.allclose(g, args.shear):
            raise ValueError(f"{source}: objects of g = ({g[0]:+.4f}, {g[1]:+.4f}), not ({args.shear[0]:+.4f}, "
                             f"{args.shear[1]:+.4f}) as the --shear given or the runs read before it: give runs "
                             "of one shear")
    if args.shear is None:
        args.shear = list(DEFAULT_SHEAR)


def _paired_bias_difference(rings, other, n_boot, rng):
    """:func:`metacal_bias_from_sums` of ``rings`` less that of ``other`` (the same galaxies, each at its own g),
    and its bootstrap error with the galaxies resampled alike in both: (estimate, error)."""
    g, g_other = np.array(rings.g, dtype=float), np.array(other.g, dtype=float)
    est = metacal_bias_from_sums(rings.sums, g)[0] - metacal_bias_from_sums(other.sums, g_other)[0]
    counts = bootstrap_counts(rings.n_galaxies, n_boot, rng)
    err = np.std(metacal_bias_from_sums(rings.sums, g, counts)[0]
                 - metacal_bias_from_sums(other.sums, g_other, counts)[0], axis=0)
    return est, err


def report_metacal_difference(rings, other, args):
    """Metacal m and c of ``rings`` less those of ``other``, a run on the same galaxies and noise (another new PSF,
    say, or another shear: each run's m is taken at its own ``g``): the same galaxies resampled for both, so that
    what they share cancels from the errors."""
    g, g_other = np.array(rings.g, dtype=float), np.array(other.g, dtype=float)
    n_gal = rings.n_galaxies
    est, err = _paired_bias_difference(rings, other, args.n_bootstrap, np.random.default_rng([args.seed, 54322]))
    shears = ("" if np.allclose(g, g_other) else
              f"; m at g = ({g[0]:+g}, {g[1]:+g}) less m at g = ({g_other[0]:+g}, {g_other[1]:+g})")
    print(f"\nmetacal, these tables less --paired-with's ({n_gal} galaxies resampled together, {args.n_bootstrap} "
          f"bootstrap resamplings{shears}):")
    print(f"  delta m1 = {format_with_error(est[0], err[0])}    delta c1 = {format_with_error(est[2], err[2])}")
    print(f"  delta m2 = {format_with_error(est[1], err[1])}    delta c2 = {format_with_error(est[3], err[3])}")
    print(f"  with the diagonal of <R> only: delta m1 = {format_with_error(est[6], err[6])}, delta m2 = "
          f"{format_with_error(est[7], err[7])}; with its mean: delta m1 = {format_with_error(est[8], err[8])}, "
          f"delta m2 = {format_with_error(est[9], err[9])}")
    if args.snr_max / args.snr_min > WIDE_SNR_RATIO and args.snr_bins > 1:
        edges = np.geomspace(args.snr_min, args.snr_max, args.snr_bins + 1)
        print("    by target SNR, with the mean of <R>'s diagonal:")
        for k, (lo, hi, sel) in enumerate(snr_bin_masks(np.asarray(rings.snr_target, float), edges)):
            n = int(sel.sum())
            if n < 2:
                continue
            d, e = _paired_bias_difference(rings.subset(sel), other.subset(sel), args.n_bootstrap,
                                           np.random.default_rng([args.seed, 54322, k]))
            print(f"      {lo:6.1f} - {hi:6.1f}  {n:6d} galaxies: delta m1 = {format_with_error(d[8], e[8])}, "
                  f"delta m2 = {format_with_error(d[9], e[9])}")


def _print_population_bias(est, err):
    """The lines of a population's metacal m and c (:func:`metacal_bias_from_sums`' estimates and errors)."""
    print(f"  m1 = {format_with_error(est[0], err[0])}    c1 = {format_with_error(est[2], err[2])}")
    print(f"  m2 = {format_with_error(est[1], err[1])}    c2 = {format_with_error(est[3], err[3])}")
    print(f"  with the diagonal of <R> only: m1 = {format_with_error(est[6], err[6])}, m2 = "
          f"{format_with_error(est[7], err[7])}; with its mean: m1 = {format_with_error(est[8], err[8])}, "
          f"m2 = {format_with_error(est[9], err[9])}")


def report_paired_population(rings, paired, other, idx, args):
    """Metacal m and c of the setting of ``rings`` on the population of ``other``, a longer campaign of another
    setting in which ``paired`` (``other``'s galaxies ``idx``) are the galaxies of ``rings`` (galaxy for galaxy,
    weighted alike): m_B(all) + [m_A - m_B](paired), a control variate (the paired difference is better measured
    than either m, so the estimate's error comes closer to that of the longer campaign). Unbiased where the paired
    galaxies are a fair sample of the population (whole seeds, or a stopped seed's first galaxies; with
    --hlr-log-uniform each side weighted to the same sizes). Errors from a bootstrap over all the galaxies of
    ``other``, the paired ones resampled alike in both."""
    g, g_other = np.array(rings.g, dtype=float), np.array(other.g, dtype=float)

    def estimate(counts=None):
        sub = None if counts is None else counts[..., idx]
        return (metacal_bias_from_sums(rings.sums, g, sub)[0] - metacal_bias_from_sums(paired.sums, g_other, sub)[0]
                + metacal_bias_from_sums(other.sums, g_other, counts)[0])

    est = estimate()
    counts = bootstrap_counts(other.n_galaxies, args.n_bootstrap, np.random.default_rng([args.seed, 54323]))
    err = np.std(estimate(counts), axis=0)
    hlr, hlr_paired = other.true_hlr, paired.true_hlr
    print(f"\nmetacal of these tables' setting on the population of --paired-with ({other.n_galaxies} galaxies, "
          f"{rings.n_galaxies} of them paired): its m there plus the paired difference above, {args.n_bootstrap} "
          f"bootstrap resamplings of all its galaxies (half-light radii {np.nanmin(hlr):.2f}-{np.nanmax(hlr):.2f}\", "
          f"the paired ones {np.nanmin(hlr_paired):.2f}-{np.nanmax(hlr_paired):.2f}\"):")
    _print_population_bias(est, err)


def _span(x):
    """'a' or 'a-b', the range of ``x`` to three decimals."""
    lo, hi = f"{np.min(x):.3f}", f"{np.max(x):.3f}"
    return lo if lo == hi else f"{lo}-{hi}"


def report_replaced_population(rings, other, idx, args):
    """Metacal m and c of the setting of ``rings`` on the whole population of ``other`` where ``rings`` measured
    only galaxies of target SNR below ``--paired-below`` (``--measure-snr-below``), and the setting is taken to leave
    the others' estimates as they are (shown where whole seeds of both settings pair: their difference there is
    zero). ``other``'s sums with those of each paired galaxy below the limit moved to the setting's, the summed move
    scaled up to all of ``other``'s galaxies below the limit (the paired ones a fair sample of them: whole seeds, or a
    stopped seed's first galaxies): with every one of them paired, the setting's own m on that population. With
    ``--hlr-log-uniform`` every galaxy weighted so in ``other``'s population, and the move scaled within each size
    bin (campaigns of small and of large galaxies rerun in different shares). Bootstrap errors over ``other``'s
    galaxies, a paired galaxy resampled with its move."""
    if not np.allclose(rings.g, other.g):
        raise ValueError(f"--paired-below: runs of g = {rings.g} and --paired-with's {other.g}: give runs of one shear")
    below = args.paired_below
    w = (hlr_log_uniform_weights(other.true_hlr, *args.hlr_log_uniform) if args.hlr_log_uniform
         else np.ones(other.n_galaxies))
    mine = rings.snr_target < below
    j = idx[mine]
    eligible = other.snr_target < below
    if not np.any(w[j] > 0):
        raise ValueError(f"--paired-below {below:g}: none of these tables' galaxies below target SNR {below:g} "
                         "counts in --paired-with's population")
    # the summed move scaled up within each size bin (the runs of 64- and 128-pixel stamps sample theirs apart)
    stratum = (hlr_bins(other.true_hlr, *args.hlr_log_uniform)[0] if args.hlr_log_uniform
               else np.zeros(other.n_galaxies, dtype=int))
    n_strata = int(stratum.max()) + 1
    total = np.bincount(stratum[eligible], weights=w[eligible], minlength=n_strata)
    measured = np.bincount(stratum[j], weights=w[j], minlength=n_strata)
    if np.any((total > 0) & (measured <= 0)):
        raise ValueError(f"--paired-below {below:g}: --paired-with's galaxies below target SNR {below:g} of "
                         f"{int(np.sum((total > 0) & (measured <= 0)))} size bin(s) have none measured here, so "
                         "their move cannot be scaled from a sample")
    scale = total[stratum[j]] / np.where(measured[stratum[j]] > 0, measured[stratum[j]], 1.0)
    moved = other.sums.copy()
    moved[:, j] += scale[None, :, None] * (rings.sums[:, mine] - other.sums[:, j])
    moved *= w[None, :, None]
    est = metacal_bias_from_sums(moved, other.g)[0]
    counts = bootstrap_counts(other.n_galaxies, args.n_bootstrap, np.random.default_rng([args.seed, 54324]))
    err = np.std(metacal_bias_from_sums(moved, other.g, counts)[0], axis=0)
    print(f"\nmetacal of these tables' setting on the population of --paired-with ({other.n_galaxies} galaxies), its "
          f"{int(eligible.sum())} below target SNR {below:g} moved to this setting ({int(mine.sum())} measured here, "
          f"their move scaled by {_span(scale[w[j] > 0])}) and the others unchanged, {args.n_bootstrap} bootstrap resamplings:")
    _print_population_bias(est, err)
    return est, err


def read_paired_rings(args):
    """The metacal galaxies of --paired-with (tables or files of galaxy sums), as one :class:`MetacalRings`."""
    files = [p for p in args.paired_with if MetacalRings.is_sums_file(p)]
    tables = [p for p in args.paired_with if p not in files]
    parts = []
    if tables:
        other, n_other = read_tables(tables)
        other_args = argparse.Namespace(**{**vars(args), "shear": table_shear(other, args.shear)})
        parts.append(MetacalRings.from_table(other, n_other, other_args))
    for path in files:
        part = MetacalRings.read(path)
        if part.weighted == bool(args.unweighted):
            raise ValueError(f"{path}: galaxy sums of {'lensfit' if part.weighted else 'unit'} weights: give the "
                             "--unweighted of the runs")
        parts.append(part)
    return MetacalRings.concatenate(parts, source=" ".join(files))


def report_plain_difference(tab, other, args, n_gal):
    """Plain lensfit m and c of ``tab`` less those of ``other``, a run on the same galaxies and noise with another
    setting (``--set``): the same galaxies resampled for both, and the objects' differences in e."""
    ok = (tab["fitclass"] == 0) & (other["fitclass"] == 0)
    de = np.stack([tab["e1"][ok] - other["e1"][ok], tab["e2"][ok] - other["e2"][ok]], axis=1)
    err = np.sqrt(other["e_var"][ok])
    g = np.array(args.shear, dtype=float)
    weighted = not args.unweighted
    sa, sb = ring_sums(tab, n_gal, weighted), ring_sums(other, n_gal, weighted)
    est = bias_from_sums(sa, g) - bias_from_sums(sb, g)
    counts = bootstrap_counts(n_gal, args.n_bootstrap, np.random.default_rng([args.seed, 54323]))
    bad = int(np.sum(tab["fitclass"] != other["fitclass"]))
    err_d = np.std(bias_from_sums(sa, g, counts) - bias_from_sums(sb, g, counts), axis=0)
    print(f"\nthese tables less --paired-with's ({n_gal} galaxies resampled together, {args.n_bootstrap} bootstrap "
          f"resamplings):")
    print(f"  delta m1 = {format_with_error(est[0], err_d[0])}    delta c1 = {format_with_error(est[2], err_d[2])}")
    print(f"  delta m2 = {format_with_error(est[1], err_d[1])}    delta c2 = {format_with_error(est[3], err_d[3])}")
    if de.size:
        print(f"  e of the {int(ok.sum())} objects measured as galaxies in both ({bad} objects' fitclass differs): "
              f"rms difference {np.sqrt(np.mean(de ** 2)):.1e}, largest {np.abs(de).max():.1e}; in units of the "
              f"error on e rms {np.sqrt(np.mean((de / err[:, None]) ** 2)):.1e}, largest "
              f"{np.max(np.abs(de).max(axis=1) / err):.1e}")


def report_lensfit(tab, args, n_gal):
    """The lensfit shear bias of the table's e. In a --metacal run those are lensfit's fits of metacal's noshear
    images (their noise is the original's processed plus the symmetrising field), so the report says so; the plain
    fits of the original images of a --with-plain run follow."""
    if args.metacal:
        print("\nlensfit on metacal's noshear images:", end="")
    report_bias(tab, args, n_gal)
    if args.metacal and "plain_e1" in tab.dtype.names:
        print("\nplain lensfit on the original images (--with-plain):", end="")
        report_bias(_plain_columns(tab), args, n_gal)


def _metacal_estimate(rings, args, rng):
    """:func:`metacal_bias_from_sums` of ``rings`` and its bootstrap errors over the galaxies: (estimate, errors,
    R_gamma, R_S)."""
    g = np.array(args.shear, dtype=float)
    est, Rg, Rs = metacal_bias_from_sums(rings.sums, g)
    counts = bootstrap_counts(rings.n_galaxies, args.n_bootstrap, rng)
    return est, np.std(metacal_bias_from_sums(rings.sums, g, counts)[0], axis=0), Rg, Rs


def report_metacal(rings, args, by_snr=True):
    """m and c of the metacal shear <R>^-1 <e> per sign (shear and selection response), bootstrap errors over
    galaxies (``rings``: a :class:`MetacalRings`); ``by_snr``: and in bins of target SNR, over a wide range."""
    n_gal = rings.n_galaxies
    est, err, Rg, Rs = _metacal_estimate(rings, args, np.random.default_rng([args.seed, 54321]))
    weights = ("every measured object, unit weights, no selection" if args.all_objects
               else "unit weights" if args.unweighted else "lensfit weights")
    print(f"\nmetacal shear bias (<R>^-1 <e> per sign, {weights}, "
          f"{args.n_bootstrap} bootstrap resamplings of {n_gal} galaxies):")
    print(f"  m1 = {format_with_error(est[0], err[0])}    c1 = {format_with_error(est[2], err[2])}")
    print(f"  m2 = {format_with_error(est[1], err[1])}    c2 = {format_with_error(est[3], err[3])}")
    print_leakage(est[2:4], err[2:4], args)
    print(f"  without the response (raw lensfit on the metacal noshear images): m1 = "
          f"{format_with_error(est[4], err[4])}, m2 = {format_with_error(est[5], err[5])}")
    print(f"  with the diagonal of <R> only (isotropic galaxies have no off-diagonal response): m1 = "
          f"{format_with_error(est[6], err[6])}, m2 = {format_with_error(est[7], err[7])}")
    print(f"  with the mean of its diagonal, (R11 + R22) / 2, for both (isotropic galaxies respond alike to either "
          f"component): m1 = {format_with_error(est[8], err[8])}, m2 = {format_with_error(est[9], err[9])}")
    root = np.sqrt(n_gal)
    print(f"  per galaxy (its whole ring): error x sqrt(galaxies) = {err[0] * root:.3f} / {err[1] * root:.3f} on m1 / "
          f"m2 (the diagonal of <R>: {err[6] * root:.3f} / {err[7] * root:.3f}; its mean: {err[8] * root:.3f} / "
          f"{err[9] * root:.3f}), so +/-7e-4 on m takes about {_galaxies_for(err[:2], root, 7e-4)} such "
          f"galaxies, +/-2e-3 about {_galaxies_for(err[:2], root, 2e-3)} (with the diagonal "
          f"{_galaxies_for(err[6:8], root, 2e-3)}, its mean {_galaxies_for(err[8:10], root, 2e-3)})")
    print(f"  <R_gamma> = [[{Rg[0, 0]:.4f}, {Rg[0, 1]:+.4f}], [{Rg[1, 0]:+.4f}, {Rg[1, 1]:.4f}]]; "
          f"R_S = [[{Rs[0, 0]:+.4f}, {Rs[0, 1]:+.4f}], [{Rs[1, 0]:+.4f}, {Rs[1, 1]:+.4f}]]")
    print(f"  fitclass != 0: {rings.n_other.sum() / max(rings.n_objects.sum(), 1):.3%} of {rings.n_objects.sum()} "
          "objects")
    if by_snr and args.snr_max / args.snr_min > WIDE_SNR_RATIO and args.snr_bins > 1:
        report_metacal_snr(rings, args)


def runs_jackknife(parts, g):
    """Metacal's bias (:func:`metacal_bias_from_sums`' estimates) of the runs ``parts`` (MetacalRings) together,
    and its delete-one-run jackknife error: each run left out in turn, ``sqrt((n - 1) / n sum (b_i - <b_i>)^2)``.
    Each run being its own seed, its galaxies, noise and PSFs independent of the others', this error does not rest
    on the galaxies' independence as the bootstrap over galaxies does. Returns (estimate, error, the n left-out
    estimates)."""
    n = len(parts)
    g = np.asarray(g, dtype=float)
    rings = MetacalRings.concatenate(parts)
    owner = np.repeat(np.arange(n), [p.n_galaxies for p in parts])
    counts = (owner[None, :] != np.arange(n)[:, None]).astype(float)   # run i's galaxies left out of row i
    left_out = metacal_bias_from_sums(rings.sums, g, counts)[0]
    err = np.sqrt((n - 1) / n * np.sum((left_out - left_out.mean(axis=0)) ** 2, axis=0))
    return metacal_bias_from_sums(rings.sums, g)[0], err, left_out


def report_runs_jackknife(parts, args):
    """m and c with the jackknife error over runs (:func:`runs_jackknife`), beside the bootstrap's."""
    if len(parts) < JACKKNIFE_MIN_RUNS:
        return
    est, err, _ = runs_jackknife(parts, args.shear)
    sizes = [p.n_galaxies for p in parts]
    print(f"\n  the same, errors from the scatter of the {len(parts)} runs (delete-one-run jackknife; runs of "
          f"{min(sizes)}-{max(sizes)} galaxies):")
    print(f"    full <R>: m1 = {format_with_error(est[0], err[0])}, m2 = {format_with_error(est[1], err[1])}; "
          f"c1 = {format_with_error(est[2], err[2])}, c2 = {format_with_error(est[3], err[3])}")
    print(f"    the mean of <R>'s diagonal: m1 = {format_with_error(est[8], err[8])}, m2 = "
          f"{format_with_error(est[9], err[9])}; lensfit on the noshear images: m1 = "
          f"{format_with_error(est[4], err[4])}, m2 = {format_with_error(est[5], err[5])}")


def report_metacal_snr(rings, args):
    """Metacal's m (the mean of <R>'s diagonal for both components) and lensfit's on the noshear images, in bins
    of the galaxies' target SNR: whether what metacal leaves grows towards the faint end, as a noise bias would."""
    edges = np.geomspace(args.snr_min, args.snr_max, args.snr_bins + 1)
    snr = np.asarray(rings.snr_target, float)
    print("\n  metacal (mean of <R>'s diagonal) and lensfit on the noshear images against target SNR (bootstrap errors):")
    print("      SNR range     n_gal          metacal m1               metacal m2               lensfit m1"
          "               lensfit m2")
    for k, (lo, hi, sel) in enumerate(snr_bin_masks(snr, edges)):
        n = int(sel.sum())
        if n < 2:
            continue
        est, err = _metacal_estimate(rings.subset(sel), args, np.random.default_rng([args.seed, 54321, k]))[:2]
        print(f"    {lo:6.1f} - {hi:6.1f}  {n:6d}   {format_with_error(est[8], err[8])}   "
              f"{format_with_error(est[9], err[9])}   {format_with_error(est[4], err[4])}   "
              f"{format_with_error(est[5], err[5])}")


def report_families(tab, args, rings=None):
    """m and c per family of galaxies outside the model family (``family`` column >= 0), and per half-light
    radius (below and above 0.3"): plain lensfit (its ``plain_*`` columns in a --with-plain metacal run)
    and, with --metacal, the metacal shear (of ``rings``, the galaxy sums). Without a table (``tab`` None: runs
    kept as galaxy sums), the metacal shear and lensfit's on the noshear images."""
    from shearfit.simulate.outside import FAMILIES

    edges = [0.0] + sorted(args.hlr_edges) + [np.inf]

    def subsets(fam, hlr):
        sizes = [(f'half-light radius < {hi:g}"' if lo == 0 else f'half-light radius >= {lo:g}"' if hi == np.inf
                  else f'half-light radius {lo:g}-{hi:g}"', (hlr >= lo) & (hlr < hi))
                 for lo, hi in zip(edges[:-1], edges[1:])]
        return [(name, fam == k) for k, name in enumerate(FAMILIES)] + sizes

    if tab is not None:
        if "family" not in tab.dtype.names or not np.any(np.asarray(tab["family"]) >= 0):
            return
        rows = subsets(np.asarray(tab["family"]), np.asarray(tab["true_hlr"], float))
    elif rings is None or not np.any(rings.family >= 0):
        return
    galaxies = subsets(rings.family, rings.true_hlr) if rings is not None else [(label, None) for label, _ in rows]
    plain = tab
    if tab is not None and args.metacal and "plain_e1" in tab.dtype.names:
        plain = _plain_columns(tab)
    for k, (label, sel_gal) in enumerate(galaxies):
        if tab is not None:
            sel = rows[k][1]
            if not sel.any():
                continue
            _, gal = np.unique(np.asarray(tab["galaxy"])[sel], return_inverse=True)
            n = int(gal.max()) + 1
        else:
            n = int(np.sum(sel_gal))
            if not n:
                continue
        print(f"\n=== {label}: {n} galaxies")
        if tab is not None and (not args.metacal or plain is not tab):
            sub = plain[sel].copy()
            sub["galaxy"] = gal
            print("  plain lensfit:", end="")
            report_bias(sub, args, n)
        if args.metacal:
            sub = rings.subset(sel_gal)
            if tab is None:
                report_lensfit_sums(sub, args)
            # the sizes' subsets with metacal's m against SNR too: whether what metacal leaves at the faint end
            # belongs to some sizes
            report_metacal(sub, args, by_snr=k >= len(FAMILIES))


def report_lensfit_sums(rings, args):
    """Lensfit's m and c on metacal's noshear images, from galaxy sums."""
    est, err = shear_bias(rings.sums[:3], np.array(args.shear, dtype=float), args.n_bootstrap,
                          np.random.default_rng([args.seed, 12345]))
    print(f"\nlensfit on metacal's noshear images ({'weighted' if rings.weighted else 'unweighted'} means, "
          f"{args.n_bootstrap} bootstrap resamplings of {rings.n_galaxies} galaxies):")
    print(f"  m1 = {format_with_error(est[0], err[0])}    c1 = {format_with_error(est[2], err[2])}")
    print(f"  m2 = {format_with_error(est[1], err[1])}    c2 = {format_with_error(est[3], err[3])}")


def report_dry(tab):
    first = tab["sign"] > 0
    t = tab[first]
    print("\nsimulated stamps (+g set; the -g set shares galaxies and noise):")
    print(f"  objects {len(t)}, galaxies {len(np.unique(t['galaxy']))}")
    for name in ("snr_target", "snr_true", "mag", "true_scalelength", "true_bulge_fraction", "sigma",
                 "peak_over_sigma", "psf_fwhm_mean", "psf_beta_mean", "n_redraws"):
        v = np.asarray(t[name], dtype=float)
        q = np.percentile(v, [0, 50, 100])
        print(f"  {name:20s} mean {v.mean():9.4f}   min {q[0]:9.4f}   median {q[1]:9.4f}   max {q[2]:9.4f}")
    emod = np.hypot(t["e1_int"], t["e2_int"])
    print(f"  {'|e_int|':20s} mean {emod.mean():9.4f}   rms per component {np.sqrt(np.mean(emod**2) / 2):.4f}")
    print(f"  bulge-dominated fraction {np.mean(t['is_bulge']):.3f}")
    ratio = t["snr_true"] / t["snr_target"]
    print(f"  SNR of each orientation / target: {ratio.min():.4f} .. {ratio.max():.4f}")


# ----------------------------------------------------------------------------- main

def build_parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--n-galaxies", type=int, default=100, help="galaxies (each gives 2 x n-rotations objects)")
    p.add_argument("--n-rotations", type=int, default=4, help="orientations per ring")
    p.add_argument("--snr-min", type=float, default=100.0)
    p.add_argument("--snr-max", type=float, default=200.0)
    p.add_argument("--mag-min", type=float, default=21.0)
    p.add_argument("--mag-max", type=float, default=24.5)
    p.add_argument("--n-exposures", type=int, default=7)
    p.add_argument("--psf-fwhm", type=float, nargs=2, default=[0.5, 0.8], metavar=("MIN", "MAX"),
                   help="Moffat FWHM range, arcsec, uniform per exposure (the closure fields: 0.55 0.85)")
    p.add_argument("--psf-e-max", type=float, default=0.1, help="PSF |e| uniform up to this (fields: 0.08)")
    p.add_argument("--psf-family", choices=["moffat", "kolmogorov"], default="moffat",
                   help="the exposures' PSF profile: elliptical Moffat (default) or elliptical Kolmogorov of the "
                        "same FWHM and ellipticity, a PSF outside the Moffat family")
    p.add_argument("--psf-e-fixed", type=float, nargs=2, default=None, metavar=("E1", "E2"),
                   help="every exposure's PSF ellipticity (e1, e2) instead of random ones: c is then the PSF "
                        "leakage, and alpha = c / e_psf is printed")
    p.add_argument("--noise-sigma", type=float, default=None,
                   help="one pixel sigma for every galaxy (counts, zero point 30) instead of the target SNR: "
                        "the SNR follows from magnitude and size as on a field (the closure fields: 4.29)")
    p.add_argument("--shear", type=float, nargs=2, default=None, metavar=("G1", "G2"),
                   help=f"the shear of the +g objects (default: {DEFAULT_SHEAR}); with --from-tables, the runs' "
                        "own, which must be one shear (given, it must be theirs)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--processes", type=int, default=os.cpu_count() or 1)
    p.add_argument("--psf-oversampling", type=int, default=1)
    p.add_argument("--stamp-size", type=int, default=48)
    p.add_argument("--rotate-exposures", action="store_true", help="random pixel-grid rotation per exposure")
    p.add_argument("--n-bootstrap", type=int, default=200)
    p.add_argument("--snr-bins", type=int, default=4, help="SNR bins for m(SNR) when snr-max/snr-min > 2.5")
    p.add_argument("--unweighted", action="store_true", help="unit weights for fitclass 0 instead of lensfit's")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="engine setting (FitConfig field), repeatable; also used for the population")
    p.add_argument("--population-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting for drawing the population only, in place of --set's (repeatable): e.g. "
                        "--set disk_e_max=0.95 --population-set disk_e_max=0.804 fits with a prior of its own "
                        "the galaxies that the paper's prior draws")
    p.add_argument("--out", help="per-object results, .fits or .csv (and, while the run lasts, its checkpoint: "
                                 "see --resume)")
    p.add_argument("--resume", action="store_true",
                   help="with --out: continue a stopped run from its checkpoint (the same options), measuring only "
                        "the galaxies it does not hold")
    p.add_argument("--galaxies", type=int, nargs="+", metavar="I",
                   help="measure only these galaxies of the seed (numbered from 0), drawn as in the whole run: "
                        "a look at a few objects of a finished run, e.g. with another setting")
    p.add_argument("--checkpoint-seconds", type=float, default=60.0,
                   help="with --out: write the checkpoint at most this often (seconds)")
    p.add_argument("--noise-free", action="store_true",
                   help="noise-free images with the weights of the target SNR: the likelihood has that SNR's "
                        "width but is centred on the truth (implementation accuracy without noise bias)")
    p.add_argument("--dry-run", action="store_true", help="simulate only and summarise the stamps")
    p.add_argument("--measure-snr-below", type=float, default=None, metavar="SNR",
                   help="draw every galaxy as usual but measure only those whose target SNR is below SNR, leaving the "
                        "others out of the tables: the same galaxies and noise as a run without it, so that a change "
                        "that acts only on faint galaxies is paired with that run at a fraction of its cost")
    p.add_argument("--population", choices=["paper", "odd", "outside"], default="paper",
                   help="the paper's population (priors), one unlike it (sizes x2, a third Sersic n=2.5, "
                        "e rms 0.3), or galaxies outside the model family (shearfit.simulate.outside: Sersic n "
                        "0.3-6, bulge + disk with their own shapes, disks with knots; half-light radius 0.1-2\"; "
                        "m and c per family too; a galaxy that would not fit its stamp is redrawn, so 64-pixel "
                        "stamps hold half-light radii up to about 0.9\" and 128-pixel ones the whole 2\")")
    p.add_argument("--population-from", nargs="+", metavar="TRUTH",
                   help="the galaxies of simulated fields (truth.fits of shearfit simulate) within the magnitude "
                        "range, drawn at random with their magnitudes, instead of new population draws")
    p.add_argument("--size-range", type=float, nargs=2, metavar=("RMIN", "RMAX"),
                   help="with the paper's population: scalelengths log-uniform from RMIN to RMAX arcsec instead "
                        "of the size prior's (benchmarks/ring_split.py --r-bins splits the result); with the "
                        "outside population: half-light radii log-uniform from RMIN to RMAX instead of 0.1-2\"")
    p.add_argument("--e-range", type=float, nargs=2, metavar=("EMIN", "EMAX"),
                   help="with the paper's population: intrinsic |e| uniform from EMIN to EMAX (position angles kept) "
                        "instead of the prior's: rings of the high-|e| tail")
    p.add_argument("--calibration", default=None,
                   help="calibration YAML for the calibrated m line (default: the paper's alpha, beta)")
    p.add_argument("--antithetic", action="store_true",
                   help="also measure every object's antithetic twin (the same galaxy, minus the noise, and minus "
                        "metacal's symmetrising noise): the terms odd in the noise cancel within each ring")
    p.add_argument("--metacal", action="store_true",
                   help="measure the five metacal versions of every object and report the metacal shear bias")
    p.add_argument("--metacal-psf", choices=["dilated", "round"], default="dilated",
                   help="with --metacal: the versions' new PSF (shearfit.calib.metacal.metacal_observations' psf)")
    p.add_argument("--metacal-fresh", action="store_true",
                   help="with --metacal: fit every sheared version on its own instead of replaying the noshear fit's "
                        "choices (shearfit.calib.metacal.measure_metacal's replay=False): R then holds the response "
                        "through the choices too")
    p.add_argument("--metacal-own-position", action="store_true",
                   help="with --metacal: the sheared versions replay every choice of the noshear fit but its position, "
                        "which each finds for itself (measure_metacal's own_position=True)")
    p.add_argument("--metacal-own-samples", action="store_true",
                   help="with --metacal: the sheared versions run the adaptive ellipticity grid on their own likelihoods "
                        "(the noshear fit's samples evaluated for all four together; measure_metacal's "
                        "own_samples=True)")
    p.add_argument("--metacal-own-sizes", action="store_true",
                   help="with --metacal: the sheared versions place their own size nodes and centres from their own "
                        "round model's size posterior (measure_metacal's own_sizes=True)")
    p.add_argument("--metacal-unsymmetrised", action="store_true",
                   help="with --metacal: metacal's added noise field processed unturned, so that the versions' whole "
                        "noise is sheared with the galaxy (shearfit.calib.metacal.SYMMETRISE_NOISE = False): paired "
                        "with a shipped run, the fits' response to the noise's shear")
    p.add_argument("--with-plain", action="store_true",
                   help="with --metacal: also measure every object with plain lensfit (columns plain_*)")
    p.add_argument("--plain", action="store_true",
                   help="with --from-tables: report the plain lensfit columns (plain_*) of --with-plain runs, "
                        "in the tables and in the reference tables")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--reference-tables", nargs="+", metavar="TABLE",
                   help="with --from-tables: a simulation calibration, the m of these ring tables (plain lensfit, "
                        "same SNR range, e.g. the paper's population) applied as (1 + m) / (1 + m_ref) - 1")
    p.add_argument("--paired-with", nargs="+", metavar="TABLE", default=None,
                   help="with --from-tables: also the m and c of these tables less those of TABLE (a run on the "
                        "same galaxies and noise with another setting), the same galaxies resampled for both (metacal's "
                        "with --metacal; else plain lensfit's, with the objects' differences in e). Galaxy sums pair "
                        "galaxy by galaxy and TABLE may hold more galaxies: then also this setting's m on all of them, "
                        "TABLE's m plus the paired difference")
    p.add_argument("--paired-below", type=float, default=None, metavar="SNR",
                   help="with --paired-with and galaxy sums: these tables measured only galaxies below target SNR "
                        "SNR (--measure-snr-below) of TABLE's population, and the setting leaves the others' estimates "
                        "as they are: this setting's m on all of TABLE's galaxies, those below SNR moved to it (their "
                        "summed move scaled up to all of them, within each size bin with --hlr-log-uniform) and the "
                        "others kept")
    p.add_argument("--from-tables", nargs="+", metavar="TABLE",
                   help="report on per-object tables written by earlier runs (--out) instead of simulating: "
                        "runs of different --seed add up (their galaxies are renumbered); give the shear, SNR "
                        "range and --metacal those runs had")
    p.add_argument("--all-objects", action="store_true",
                   help="with --from-tables and --metacal (per-object tables): no selection, for simulations without "
                        "stars: every object whose e and R were measured counts with unit weight in every version, "
                        "whatever its fitclass, so that the selection response is zero and m is the shear response's "
                        "alone (about half the error of the star cut's m at SNR 10-40)")
    p.add_argument("--hlr-log-uniform", type=float, nargs=2, metavar=("LO", "HI"),
                   help="with --from-tables and --metacal: weight the galaxies so that their half-light radii are "
                        "log-uniform from LO to HI (the inverse of their number per bin of ln hlr; those outside "
                        "weigh 0): runs of different --size-range and --stamp-size as one population")
    p.add_argument("--hlr-edges", type=float, nargs="+", default=[0.3], metavar="HLR",
                   help="with --population outside (or its tables): the half-light radii (arcsec) that split the "
                        "galaxies into the size subsets of the report, each with metacal's m against SNR")
    p.add_argument("--save-sums", metavar="FILE",
                   help="with --from-tables and --metacal: also write the galaxy sums of what was read to FILE "
                        "(about 180 bytes per galaxy; --from-tables reads it as it reads tables, so a long "
                        "campaign can be kept and reported without its per-object tables)")
    return p


def parse_args(argv=None):
    p = build_parser()
    args = p.parse_args(argv)
    if args.shear is None and not args.from_tables:
        args.shear = list(DEFAULT_SHEAR)
    if args.save_sums and not args.from_tables:
        p.error("--save-sums needs --from-tables")
    if any(not h > 0 for h in args.hlr_edges):
        p.error("--hlr-edges must be positive")
    if args.hlr_log_uniform and (not args.from_tables or not args.metacal or args.save_sums
                                 or not 0 < args.hlr_log_uniform[0] < args.hlr_log_uniform[1]):
        p.error("--hlr-log-uniform needs --from-tables, --metacal, no --save-sums, and 0 < LO < HI")
    if args.n_galaxies < 1 or args.n_rotations < 1 or args.n_exposures < 1 or args.processes < 1:
        p.error("--n-galaxies, --n-rotations, --n-exposures and --processes must be positive")
    if not 0 < args.snr_min <= args.snr_max:
        p.error("need 0 < --snr-min <= --snr-max")
    if args.size_range is not None and (args.population not in ("paper", "outside")
                                        or not 0 < args.size_range[0] < args.size_range[1]):
        p.error("--size-range needs 0 < RMIN < RMAX and the paper's or the outside population")
    if args.e_range is not None and (args.population != "paper" or args.population_from
                                     or not 0 <= args.e_range[0] < args.e_range[1] < 1):
        p.error("--e-range needs 0 <= EMIN < EMAX < 1 and the paper's population")
    if args.metacal_fresh and not args.metacal:
        p.error("--metacal-fresh needs --metacal")
    if args.metacal_own_position and not (args.metacal and not args.metacal_fresh):
        p.error("--metacal-own-position needs --metacal, without --metacal-fresh")
    if args.metacal_own_samples and not (args.metacal and not args.metacal_fresh):
        p.error("--metacal-own-samples needs --metacal, without --metacal-fresh")
    if args.metacal_own_sizes and not (args.metacal and not args.metacal_fresh):
        p.error("--metacal-own-sizes needs --metacal, without --metacal-fresh")
    if args.metacal_unsymmetrised and not args.metacal:
        p.error("--metacal-unsymmetrised needs --metacal")
    if args.noise_free and args.metacal:
        p.error("--noise-free with --metacal: metacal's symmetrising noise would be the images' only noise, and "
                "nothing cancels its processed correlation (a biased response); benchmarks/metacal_noise_free.py "
                "measures metacal without noise")
    if args.resume and not args.out:
        p.error("--resume needs --out (the run whose checkpoint it continues)")
    return args


#: options that do not change what a run's galaxies are or how they are measured (a checkpoint continues under
#: other values of these)
_RUN_ONLY_OPTIONS = {"out", "resume", "checkpoint_seconds", "processes", "quiet", "n_bootstrap", "snr_bins", "save_sums",
                     "unweighted", "all_objects", "calibration", "hlr_log_uniform", "hlr_edges"}


def run_signature(args):
    """A short digest of the options that decide a run's galaxies and measurements (a checkpoint records it and
    --resume checks it). Options at their defaults are left out, so that an option added later (at a default that
    keeps what runs did before) does not orphan the checkpoints of earlier runs."""
    import hashlib

    defaults = vars(build_parser().parse_args([]))
    items = sorted((k, v) for k, v in vars(args).items()
                   if k not in _RUN_ONLY_OPTIONS and (k not in defaults or v != defaults[k]))
    return hashlib.sha1(repr(items).encode()).hexdigest()[:16]


def _record_order(rec):
    """The per-object table's row order: galaxy, +g before -g, orientation (twins after the first members)."""
    return rec["galaxy"], -rec["sign"], rec["rotation"]


def checkpoint_path(out):
    """The checkpoint of the table ``out``: T.partial.fits for T.fits (T.partial.csv for T.csv)."""
    stem, ext = os.path.splitext(out)
    return f"{stem}.partial{ext or '.fits'}"


def read_checkpoint(path, signature):
    """The records of a checkpoint (a list of dicts, galaxy by galaxy), after checking it belongs to this run."""
    from astropy.table import Table

    try:
        t = Table.read(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the checkpoint ({exc})") from None
    got = t.meta.get("RUNSIG")
    if got != signature:
        raise ValueError(f"{path}: checkpoint of another run (header RUNSIG {got!r}, this run's {signature!r}): "
                         "give the options of the run that wrote it, or remove it")
    names = t.colnames
    cols = [np.asarray(t[n]) for n in names]
    return [{n: (str(c[i]) if c.dtype.kind == "U" else c[i].item()) for n, c in zip(names, cols)}
            for i in range(len(t))]


def _config(settings):
    from shearfit.config import settings_from_items

    return shearfit.fit_config_from_mapping(settings_from_items(settings))


def _write_table(tab, path, meta=None):
    from astropy.table import Table

    t = Table({k: tab[k] for k in tab.dtype.names}, meta=meta or {})
    tmp = f"{path}.tmp{os.getpid()}"
    fmt = "csv" if path.lower().endswith(".csv") else "fits"
    try:
        t.write(tmp, format=fmt if fmt == "fits" else "ascii.csv", overwrite=True)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _to_array(records):
    names = list(records[0])
    cols = {}
    for n in names:
        vals = [r[n] for r in records]
        cols[n] = np.array(vals, dtype="U200") if n == "error" else np.array(vals)
    arr = np.zeros(len(records), dtype=[(n, cols[n].dtype) for n in names])
    for n in names:
        arr[n] = cols[n]
    return arr


def stars_kept(t):
    """``t`` (a table or a mapping of columns) with the objects classified as stars (fitclass 1) counted as galaxies,
    at the weight of their e_var: the measurement without the star/galaxy selection, which selects on shape (an
    elongated small galaxy beats a point source by more) and so responds to the shear."""
    star = np.asarray(t["fitclass"]) == 1
    weight = np.where(star, lensing_weight(np.asarray(t["e_var"], float), FitConfig()), np.asarray(t["weight"], float))
    fitclass = np.where(star, 0, np.asarray(t["fitclass"]))
    if isinstance(t, dict):
        return dict(t, weight=weight, fitclass=fitclass)
    t = t.copy()
    t["weight"], t["fitclass"] = weight, fitclass
    return t


def read_tables(paths, shears=None):
    """Several runs' per-object tables as one (galaxies renumbered 0..n-1): (array, n_galaxies). Only the
    columns every table has are kept (the others are named on stderr): a column that some runs did not write
    (``plain_*`` of --with-plain, metacal's) would otherwise be filled with placeholders for their objects.
    ``shears``, a list: each table's (path, shear of its +g objects or None) is appended to it."""
    from astropy.table import Table, vstack

    parts, offset = [], 0
    for path in paths:
        t = Table.read(path)
        if shears is not None:
            shears.append((path, table_shear(t, None)))
        t["galaxy"] = np.asarray(t["galaxy"]) + offset
        offset = int(np.max(t["galaxy"])) + 1
        parts.append(t)
    common = set.intersection(*(set(t.colnames) for t in parts))
    partial = sorted(set().union(*(t.colnames for t in parts)) - common)
    if partial:
        print(f"ring_test.py: columns not in every table, left out: {', '.join(partial)}", file=sys.stderr)
    tab = np.asarray(vstack(parts, join_type="inner").as_array())
    # the reports index rings by galaxy number
    _, tab["galaxy"] = np.unique(tab["galaxy"], return_inverse=True)
    return tab, int(tab["galaxy"].max()) + 1


def _plain_columns(tab):
    """A --with-plain table with its plain lensfit columns in the places of the measured ones."""
    out = tab.copy()
    for name in RESULT_FIELDS + ("fitclass",):
        if name in NEWER_FIELDS and f"plain_{name}" not in tab.dtype.names:
            continue
        if f"plain_{name}" not in tab.dtype.names:
            raise KeyError(f"no column plain_{name}: the tables were not written by a --with-plain run")
        out[name] = tab[f"plain_{name}"]
    return out


def report_tables(args):
    """The reports of several earlier runs' per-object tables (or metacal runs' galaxy sums), as one run."""
    sums_files = [p for p in args.from_tables if MetacalRings.is_sums_file(p)]
    tables = [p for p in args.from_tables if p not in sums_files]
    if (sums_files or args.save_sums) and (not args.metacal or args.plain or args.reference_tables):
        print("ring_test.py: error: galaxy sums (--save-sums, or a file of them in --from-tables) are metacal's: "
              "give --metacal, and neither --plain nor --reference-tables", file=sys.stderr)
        return 2
    if args.all_objects and (not args.metacal or sums_files or args.save_sums):
        print("ring_test.py: error: --all-objects re-selects the objects of per-object metacal tables: give --metacal "
              "and tables only (no galaxy sums, no --save-sums)", file=sys.stderr)
        return 2
    if args.paired_below is not None and not (sums_files and args.paired_with):
        print("ring_test.py: error: --paired-below moves --paired-with's galaxies below an SNR to these runs': give "
              "--paired-with and files of galaxy sums (--save-sums) in --from-tables", file=sys.stderr)
        return 2
    if args.hlr_log_uniform and not sums_files:
        print("ring_test.py: error: --hlr-log-uniform weights galaxy sums: give at least one file of them "
              "(--save-sums) in --from-tables", file=sys.stderr)
        return 2
    try:
        found = []
        tab, n_gal = read_tables(tables, found) if tables else (None, 0)
        ref = read_tables(args.reference_tables, found) if args.reference_tables else None
        sums = [MetacalRings.read(path) for path in sums_files]   # read once: the shear, then the report
        if args.shear is None and not found and sums:
            found.append((sums_files[0], sums[0].g))
        resolve_shear(args, found)
        if args.plain:
            tab = _plain_columns(tab)
            ref = (_plain_columns(ref[0]), ref[1]) if ref is not None else None
            args.metacal = False
        rings = None
        if args.metacal:
            parts = [MetacalRings.from_table(tab, n_gal, args)] if tab is not None else []
            for path, part in zip(sums_files, sums):
                try:
                    _metacal_check(part, args)
                except ValueError as exc:
                    raise ValueError(f"{path}: {exc}") from None
                parts.append(part)
            rings = unweighted = MetacalRings.concatenate(parts, source=" ".join(sums_files))
            if args.hlr_log_uniform:
                # each run weighted by its galaxies' share of the weights found on all of them (the jackknife
                # over runs needs the runs weighted too), then put together again
                w = hlr_log_uniform_weights(rings.true_hlr, *args.hlr_log_uniform)
                ends = np.cumsum([0] + [p.n_galaxies for p in parts])
                parts = [p.weighted_by(w[a:b]) for p, a, b in zip(parts, ends[:-1], ends[1:])]
                rings = MetacalRings.concatenate(parts)
                print(f"galaxies weighted to half-light radii log-uniform over {args.hlr_log_uniform[0]:g}-"
                      f"{args.hlr_log_uniform[1]:g}\": {int(np.sum(w > 0))} of {w.size} within it, weights "
                      f"{w[w > 0].min():.3f}-{w.max():.3f}")
    except (OSError, ValueError, KeyError) as exc:
        print(f"ring_test.py: error: {exc}", file=sys.stderr)
        return 2
    if args.save_sums:
        rings.write(args.save_sums, args.from_tables)
        print(f"galaxy sums of {rings.n_galaxies} galaxies written to {args.save_sums}")
    if sums_files:
        paired = None
        if args.paired_with:
            try:
                other = whole = read_paired_rings(args)
                idx = unweighted.match_in(other, source="--paired-with")
                theirs = other.subset(idx)
                if args.hlr_log_uniform:
                    # the paired galaxies weighted as these runs' own (log-uniform among themselves, the other
                    # setting's with the same weights galaxy for galaxy); the other's whole population as its own
                    theirs = theirs.weighted_by(w)   # the weights the runs' own report was given above
                    other = other.weighted_by(hlr_log_uniform_weights(other.true_hlr, *args.hlr_log_uniform))
                paired = theirs, other, idx, whole
            except (OSError, ValueError, KeyError) as exc:
                print(f"ring_test.py: error: {exc}", file=sys.stderr)
                return 2
        print(f"ring test from {len(tables)} table(s) and {len(sums_files)} file(s) of galaxy sums: "
              f"{rings.n_galaxies} galaxies, {rings.n_objects.sum()} objects")
        report_lensfit_sums(rings, args)
        report_metacal(rings, args)
        report_runs_jackknife(parts, args)
        if paired is not None:
            theirs, other, idx, whole = paired
            report_metacal_difference(rings, theirs, args)
            if args.paired_below is not None:
                try:
                    report_replaced_population(unweighted, whole, idx, args)
                except ValueError as exc:
                    print(f"ring_test.py: error: {exc}", file=sys.stderr)
                    return 2
            elif other.n_galaxies > rings.n_galaxies:
                report_paired_population(rings, theirs, other, idx, args)
        report_families(None, args, rings)
        return 0
    print(f"ring test from {len(args.from_tables)} table(s): {n_gal} galaxies, {len(tab)} objects")
    report_lensfit(tab, args, n_gal)
    if ref is not None:
        g = np.array(args.shear, dtype=float)
        rng = np.random.default_rng([args.seed, 777])
        weighted = not args.unweighted
        est, err = shear_bias(ring_sums(tab, n_gal, weighted), g, args.n_bootstrap, rng)
        est_r, err_r = shear_bias(ring_sums(ref[0], ref[1], weighted), g, args.n_bootstrap, rng)
        cal = (1 + est[:2]) / (1 + est_r[:2]) - 1
        cal_err = np.hypot(err[:2], (1 + est[:2]) * err_r[:2] / (1 + est_r[:2])) / (1 + est_r[:2])
        print(f"  calibrated by the simulations of {len(args.reference_tables)} reference table(s) ({ref[1]} galaxies, "
              f"m_ref = {est_r[0]:+.5f} / {est_r[1]:+.5f}): m1 = {format_with_error(cal[0], cal_err[0])}, "
              f"m2 = {format_with_error(cal[1], cal_err[1])}")
    if args.metacal:
        report_metacal(rings, args)
    if args.paired_with:
        try:
            other, n_other = read_tables(args.paired_with)
            if args.plain:
                other = _plain_columns(other)
        except (OSError, ValueError, KeyError) as exc:
            print(f"ring_test.py: error: {exc}", file=sys.stderr)
            return 2
        if n_other != n_gal or len(other) != len(tab):
            print(f"ring_test.py: error: --paired-with: {n_other} galaxies and {len(other)} objects, not "
                  f"{n_gal} and {len(tab)}", file=sys.stderr)
            return 2
        if args.metacal:
            # the other run's own shear (a run at another g on the same galaxies and noise: m's shear dependence)
            other_args = argparse.Namespace(**{**vars(args), "shear": table_shear(other, args.shear)})
            report_metacal_difference(rings, MetacalRings.from_table(other, n_other, other_args), args)
        else:
            report_plain_difference(tab, other, args, n_gal)
    report_families(tab, args, rings)
    return 0


def main(argv=None):
    args = parse_args(argv)
    try:
        cfg = _config(args.set)
        pop_cfg = _config(args.set + args.population_set) if args.population_set else cfg
    except (ValueError, KeyError) as exc:
        print(f"ring_test.py: error: {exc}", file=sys.stderr)
        return 2
    if not args.dry_run:
        try:
            _get_measure_object()
        except RuntimeError as exc:
            print(f"ring_test.py: error: {exc}", file=sys.stderr)
            return 2
    if args.from_tables:
        return report_tables(args)
    if args.paired_below is not None:
        print("ring_test.py: error: --paired-below reads runs: give --from-tables", file=sys.stderr)
        return 2
    opts = {
        "shear": tuple(args.shear), "dry_run": args.dry_run, "config": cfg, "metacal": args.metacal,
        "population_config": pop_cfg,
        "measure_snr_below": args.measure_snr_below,
        "metacal_psf": args.metacal_psf, "metacal_fresh": args.metacal_fresh,
        "metacal_own_position": args.metacal_own_position, "metacal_own_samples": args.metacal_own_samples,
        "metacal_own_sizes": args.metacal_own_sizes,
        "metacal_unsymmetrised": args.metacal_unsymmetrised,
        "antithetic": args.antithetic, "with_plain": args.with_plain and args.metacal,
        "ring_kwargs": dict(n_rotations=args.n_rotations, n_exposures=args.n_exposures,
                            snr_range=(args.snr_min, args.snr_max), mag_range=(args.mag_min, args.mag_max),
                            psf_fwhm_range=tuple(args.psf_fwhm), psf_e_max=args.psf_e_max,
                            psf_family=args.psf_family,
                            psf_e_fixed=tuple(args.psf_e_fixed) if args.psf_e_fixed else None,
                            noise_sigma=args.noise_sigma,
                            stamp_size=args.stamp_size, psf_oversampling=args.psf_oversampling,
                            rotate_exposures=args.rotate_exposures, add_noise=not args.noise_free,
                            population=(functools.partial(outside_population, hlr_range=tuple(args.size_range))
                                        if args.size_range and args.population == "outside" else
                                        functools.partial(sized_population, size_range=tuple(args.size_range))
                                        if args.size_range else
                                        functools.partial(replayed_population, galaxies=truth_galaxies(
                                            args.population_from, (args.mag_min, args.mag_max)))
                                        if args.population_from else
                                        {"odd": odd_population, "outside": outside_population}.get(args.population))
                            if args.e_range is None else functools.partial(
                                e_ranged_population, e_range=tuple(args.e_range),
                                base=functools.partial(sized_population, size_range=tuple(args.size_range))
                                if args.size_range else None),
                            profile=outside_profile if args.population == "outside" else None),
    }
    seeds = np.random.SeedSequence(args.seed).spawn(args.n_galaxies)
    signature = run_signature(args)
    ckpt = checkpoint_path(args.out) if args.out else None
    records = []
    if ckpt and os.path.exists(ckpt):
        if not args.resume:
            print(f"ring_test.py: error: {ckpt} exists (a stopped run's checkpoint): add --resume to continue "
                  "it, or remove it", file=sys.stderr)
            return 2
        try:
            records = read_checkpoint(ckpt, signature)
        except ValueError as exc:
            print(f"ring_test.py: error: {exc}", file=sys.stderr)
            return 2
    done = {int(r["galaxy"]) for r in records}
    wanted = range(args.n_galaxies)
    if args.galaxies:
        bad = [i for i in args.galaxies if not 0 <= i < args.n_galaxies]
        if bad:
            print(f"ring_test.py: error: --galaxies {bad[0]} is not a galaxy of the run (0 to {args.n_galaxies - 1})",
                  file=sys.stderr)
            return 2
        wanted = sorted(set(args.galaxies))
    tasks = [(i, seeds[i], opts) for i in wanted if i not in done]
    n_proc = max(min(args.processes, len(tasks)), 1)
    print(f"ring test: {args.n_galaxies} galaxies x {args.n_rotations} orientations x 2 shears "
          f"(g = {args.shear[0]:+.4f}, {args.shear[1]:+.4f}), {args.n_exposures} exposures, "
          f"SNR {args.snr_min:g}-{args.snr_max:g}, {n_proc} process(es){', dry run' if args.dry_run else ''}"
          + (f"; {len(done)} galaxies from the checkpoint {ckpt}" if done else ""))

    t_sim, t_meas, n_new = 0.0, 0.0, 0
    t_wall = time.perf_counter()
    t_saved = t_wall
    show = not args.quiet and sys.stderr.isatty()

    def save_checkpoint():
        if ckpt and records:
            _write_table(_to_array(sorted(records, key=_record_order)), ckpt, meta={"RUNSIG": signature})

    def collect(results):
        nonlocal t_sim, t_meas, n_new, t_saved
        for k, (recs, ts, tm) in enumerate(results, 1):
            records.extend(recs)
            n_new += len(recs)
            t_sim += ts
            t_meas += tm
            if show:
                print(f"\r  {k}/{len(tasks)} galaxies", end="", file=sys.stderr, flush=True)
            if ckpt and time.perf_counter() - t_saved >= args.checkpoint_seconds:
                save_checkpoint()
                t_saved = time.perf_counter()
        if show:
            print(file=sys.stderr)

    def stop(signum, frame):   # SIGTERM as ^C: the checkpoint is written before the process ends
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop) if ckpt else None
    try:
        if n_proc == 1:
            collect(map(_work, tasks))
        else:
            with Pool(n_proc, initializer=signal.signal, initargs=(signal.SIGTERM, signal.SIG_DFL)) as pool:
                collect(pool.imap_unordered(_work, tasks, chunksize=1))
    except KeyboardInterrupt:
        save_checkpoint()
        if ckpt:
            print(f"\nring_test.py: interrupted; {len({r['galaxy'] for r in records})} galaxies kept in {ckpt} "
                  "(the same command with --resume continues)", file=sys.stderr)
        return 130
    finally:
        if previous is not None:   # main() may run inside another program (the tests)
            signal.signal(signal.SIGTERM, previous)
    t_wall = time.perf_counter() - t_wall

    records.sort(key=_record_order)
    tab = _to_array(records)
    # the timing is this process's: the objects it simulated and measured (not a checkpoint's)
    n_orient = max(n_new, 1)  # one orientation of one galaxy at one shear = one simulated object
    print(f"\ntiming: wall {t_wall:.1f} s; simulation {t_sim / n_orient * 1e3:.1f} ms per "
          f"{args.n_exposures}-exposure object (one process)", end="")
    if args.dry_run:
        print()
        report_dry(tab)
    else:
        rate = n_new / t_meas if t_meas > 0 else np.nan
        print(f"; measurement {t_meas / n_orient * 1e3:.1f} ms per object = {rate:.2f} galaxies / s / process")
        report_lensfit(tab, args, args.n_galaxies)
        rings = MetacalRings.from_table(tab, args.n_galaxies, args) if args.metacal else None
        if args.metacal:
            report_metacal(rings, args)
        report_families(tab, args, rings)
    if args.out:
        _write_table(tab, args.out)
        if os.path.exists(ckpt):
            os.remove(ckpt)
        print(f"\nper-object results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
