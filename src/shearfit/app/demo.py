"""``shearfit demo``: the whole pipeline on a small simulated field.

Simulates (``shearfit simulate``, preset ``small``) the same field twice,
with shear +g and -g (same galaxies, 90-degree pairs, PSFs and noise), fits
the PSF models from the stars and measures every object
(the library call behind ``shearfit measure``), then matches the galaxies to the truth and prints
the input shear, the recovered shear (the weighted mean ellipticity of the
objects classified as galaxies, as a user would compute it) and the
multiplicative and additive biases m and c from the galaxies measured in
both fields, raw and calibrated by the catalogue's m(snr, scalelength / psf_fwhm) column
(divided by 1 + K, K its weighted mean, as for a shear estimate):
``m_k = (sum w+ e+ / sum w+ - sum w- e- / sum w-) / (2 g_k) - 1``, the response
of the weighted mean ellipticity with each field's own weights (lensfit's
weight depends on |e| and responds to the shear too), and
``c_k = sum w (d+ + d-) / (2 sum w)`` with d = e - e_int, e_int the intrinsic
ellipticity, so that shape noise and most of the pixel noise cancel; errors
are bootstrap resamplings of the galaxy pairs (a galaxy with its 90-degree
twin).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from ..calib.bias import ring_sums, shear_bias
from ..calib.calibrate import matched_galaxies
from ..io.fieldconfig import load_field_config
from ..pipeline.driver import measure_field
from ..errors import ShearfitValueError
from ..simulate.field import simulate_field, simulation_config

__all__ = ["run_field_demo"]

DEMO_SHEAR = (0.04, -0.03)


def _pair_bias(tp, tm, g, n_boot=500, seed=0):
    """m and c (both components) from the +g and -g measurements of the same galaxies, bootstrap errors over
    90-degree pairs; and K, the weighted mean of the catalogue's calibration m over the galaxies."""
    ids = np.intersect1d(np.asarray(tp["id"]), np.asarray(tm["id"]))
    ip = {int(i): k for k, i in enumerate(tp["id"])}
    im = {int(i): k for k, i in enumerate(tm["id"])}
    a = np.array([ip[int(i)] for i in ids], int)
    b = np.array([im[int(i)] for i in ids], int)
    wp, wm = np.asarray(tp["weight"], float)[a], np.asarray(tm["weight"], float)[b]
    w = 0.5 * (wp + wm)
    # a galaxy and its 90-degree twin are resampled together: they are one "galaxy" of the ring sums
    pair = np.unique(ids // 2, return_inverse=True)[1]
    n_pair = int(pair.max()) + 1 if ids.size else 0
    base = {"galaxy": np.concatenate([pair, pair]), "sign": np.repeat([1, -1], ids.size),
            "fitclass": np.zeros(2 * ids.size, int)}
    # m: the weighted mean ellipticity's response, each field's own weights (which respond to the shear too)
    resp = dict(base, weight=np.concatenate([wp, wm]))
    # c: measured minus intrinsic ellipticity (the same e_int in both fields), so that the shape noise cancels
    resid = dict(base, weight=np.concatenate([w, w]))
    for k in (1, 2):
        ep, em = np.asarray(tp[f"e{k}"], float)[a], np.asarray(tm[f"e{k}"], float)[b]
        resp[f"e{k}"] = np.concatenate([ep, em])
        resid[f"e{k}"] = np.concatenate([ep - np.asarray(tp[f"e{k}_int"], float)[a],
                                         em - np.asarray(tm[f"e{k}_int"], float)[b]])
    est, err = shear_bias(ring_sums(resp, n_pair), g, n_boot, np.random.default_rng(seed))
    est_c, err_c = shear_bias(ring_sums(resid, n_pair), g, n_boot, np.random.default_rng(seed))
    est[2:], err[2:] = est_c[2:], err_c[2:]
    m_cal = 0.5 * (np.asarray(tp["m"], float)[a] + np.asarray(tm["m"], float)[b])
    K = float(np.sum(w * m_cal) / np.sum(w)) if ids.size else float("nan")
    return est, err, int(ids.size), K


def run_field_demo(out_dir=None, processes=None, seed=1, quiet=False, psf="fitted", preset="small",
                   shear=DEMO_SHEAR, stream=None) -> dict:
    """Simulate, fit PSFs, measure and report (see the module doc). Returns the summary dict."""
    from astropy.table import Table

    stream = stream or sys.stdout
    if psf not in ("fitted", "true"):
        raise ShearfitValueError(f"psf must be 'fitted' or 'true', got {psf!r}")
    out_dir = os.path.abspath(out_dir or "shearfit_demo")
    processes = processes or os.cpu_count() or 1
    say = (lambda *a: print(*a, file=stream, flush=True)) if not quiet else (lambda *a: None)
    t0 = time.time()
    tables, truths = {}, {}
    for name, sign in (("plus", 1.0), ("minus", -1.0)):
        d = os.path.join(out_dir, f"field_{name}")
        sc = simulation_config({"preset": preset, "seed": seed, "shear": [sign * shear[0], sign * shear[1]]})
        ts = time.time()
        res = simulate_field(sc, d)
        say(f"simulated {d}: {res['n_galaxies']} galaxies, {res['n_stars']} stars, {sc.n_exposures} exposures x "
            f"{sc.n_ccd} CCDs, shear ({sign * shear[0]:+.3f}, {sign * shear[1]:+.3f}) in {time.time() - ts:.0f} s")
        config = os.path.join(d, "field.yaml" if psf == "fitted" else "field_truepsf.yaml")
        out = os.path.join(d, "shear.fits")
        ts = time.time()
        measure_field(load_field_config(config), out_path=out, processes=processes)
        say(f"measured {d} ({'PSF fitted from the stars' if psf == 'fitted' else 'true PSF given'}) "
            f"in {time.time() - ts:.0f} s: {out}")
        tables[name] = Table.read(out)
        truths[name] = matched_galaxies(out, res["truth"])
    # the recovered shear as a user computes it: weighted mean e of everything classified as a galaxy
    cat = tables["plus"]
    gal = (np.asarray(cat["fitclass"]) == 0) & (np.asarray(cat["weight"]) > 0)
    w = np.asarray(cat["weight"], float)[gal]
    e = np.stack([np.asarray(cat["e1"], float)[gal], np.asarray(cat["e2"], float)[gal]], 1)
    rec = np.sum(w[:, None] * e, 0) / w.sum()
    rng = np.random.default_rng(seed)
    boot = [np.sum(w[s, None] * e[s], 0) / w[s].sum() for s in (rng.integers(0, w.size, w.size) for _ in range(500))]
    rec_err = np.std(boot, axis=0)
    truth_plus = Table.read(os.path.join(out_dir, "field_plus", "truth.fits"))
    star_ids = set(np.asarray(truth_plus["id"])[np.asarray(truth_plus["is_star"], bool)].tolist())
    n_star_as_gal = int(sum(int(i) in star_ids for i in np.asarray(cat["id"])[gal]))
    (m1, m2, c1, c2), (sm1, sm2, sc1, sc2), n_pairs, K = _pair_bias(truths["plus"], truths["minus"], shear)
    # calibrated as a user calibrates a shear estimate: divided by 1 + K, K the weighted mean of the
    # catalogue's m(snr, scalelength / psf_fwhm) (paper sec. 8.4-8.5); its error is the raw error scaled alike
    mc1, mc2 = (1 + m1) / (1 + K) - 1, (1 + m2) / (1 + K) - 1
    summary = dict(out_dir=out_dir, input_shear=list(shear), recovered_shear=rec.tolist(),
                   recovered_shear_err=rec_err.tolist(), m=[m1, m2], m_err=[sm1, sm2], c=[c1, c2], c_err=[sc1, sc2],
                   m_calibrated=[mc1, mc2], m_calibrated_err=[sm1 / (1 + K), sm2 / (1 + K)], mean_calibration_m=K,
                   n_galaxies=n_pairs, n_classified_galaxies=int(gal.sum()), n_stars_as_galaxies=n_star_as_gal,
                   psf=psf, seed=seed, wall_s=time.time() - t0, processes=processes)
    say("")
    say(f"input shear       g1 = {shear[0]:+.4f}             g2 = {shear[1]:+.4f}")
    say(f"recovered shear   g1 = {rec[0]:+.4f} +- {rec_err[0]:.4f}   g2 = {rec[1]:+.4f} +- {rec_err[1]:.4f}   "
        f"weighted mean e, field +g")
    say(f"multiplicative    m1 = {mc1:+.4f} +- {sm1 / (1 + K):.4f}   m2 = {mc2:+.4f} +- {sm2 / (1 + K):.4f}   "
        f"calibrated (1 + K = {1 + K:.4f})")
    say(f"                  m1 = {m1:+.4f} +- {sm1:.4f}   m2 = {m2:+.4f} +- {sm2:.4f}   raw")
    say(f"additive          c1 = {c1:+.4f} +- {sc1:.4f}   c2 = {c2:+.4f} +- {sc2:.4f}")
    say("")
    say(f"- recovered shear: the weighted mean ellipticity of the {int(gal.sum())} objects classified as "
        f"galaxies ({n_star_as_gal} of them simulated stars); its error is mostly shape noise")
    say(f"- m and c: the {n_pairs} simulated galaxies measured in both the +g and -g fields; m the response of "
        "their weighted mean ellipticity, c from it minus their intrinsic ellipticity (errors: bootstrap over "
        "90-degree pairs)")
    say("- raw m is lensfit's noise bias (the likelihood-mean estimator is biased low at low SNR); the catalogue's "
        "m column holds the calibration m(snr, scalelength / psf_fwhm), and dividing by 1 + K, K its weighted mean, "
        "calibrates it")
    say(f"outputs: {out_dir}/field_plus and field_minus (exposures, field.yaml, truth.fits, shear.fits); "
        f"total {time.time() - t0:.0f} s on {processes} process(es)")
    return summary
