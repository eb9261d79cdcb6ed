"""``shearfit demo``: the whole pipeline on a small simulated field.

Simulates (``shearfit simulate``, preset ``small``) the same field twice,
with shear +g and -g (same galaxies, 90-degree pairs, PSFs and noise), fits
the PSF models from the stars and measures every object
(``shearfit measure``), then matches the galaxies to the truth and prints
the input shear, the recovered shear (the weighted mean ellipticity of the
objects classified as galaxies, as a user would compute it) and the
multiplicative and additive biases m and c from the galaxies measured in
both fields: with e_int the intrinsic ellipticity,
``m_k = sum w (d+ - d-) / (2 g_k sum w) - 1`` and ``c_k = sum w (d+ + d-) / (2 sum w)``
with d = e - e_int,
so that shape noise and most of the pixel noise cancel; errors are
bootstrap resamplings of the galaxy pairs.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from .calibrate import matched_galaxies
from .cli import main as cli_main
from .errors import ShearfitValueError
from .simulate.field import simulate_field, simulation_config

__all__ = ["run_field_demo"]

DEMO_SHEAR = (0.04, -0.03)


def _pair_bias(tp, tm, g, n_boot=500, seed=0):
    """m and c (both components) from the +g and -g measurements of the same galaxies, bootstrap errors."""
    ids = np.intersect1d(np.asarray(tp["id"]), np.asarray(tm["id"]))
    ip = {int(i): k for k, i in enumerate(tp["id"])}
    im = {int(i): k for k, i in enumerate(tm["id"])}
    a = np.array([ip[int(i)] for i in ids], int)
    b = np.array([im[int(i)] for i in ids], int)
    w = 0.5 * (np.asarray(tp["weight"], float)[a] + np.asarray(tm["weight"], float)[b])
    # measured minus intrinsic ellipticity (the same e_int in both fields)
    dp = np.stack([np.asarray(tp[f"e{k}"], float)[a] - np.asarray(tp[f"e{k}_int"], float)[a] for k in (1, 2)], 1)
    dm = np.stack([np.asarray(tm[f"e{k}"], float)[b] - np.asarray(tm[f"e{k}_int"], float)[b] for k in (1, 2)], 1)
    pair = ids // 2          # a galaxy and its 90-degree twin are resampled together

    def est(sel):
        ww = w[sel][:, None]
        s = ww.sum()
        m = np.sum(ww * (dp[sel] - dm[sel]), 0) / (2 * np.asarray(g) * s) - 1
        c = np.sum(ww * (dp[sel] + dm[sel]), 0) / (2 * s)
        return np.concatenate([m, c])

    rng = np.random.default_rng(seed)
    upairs = np.unique(pair)
    members = {p: np.nonzero(pair == p)[0] for p in upairs}
    boots = [est(np.concatenate([members[p] for p in rng.choice(upairs, upairs.size)])) for _ in range(n_boot)]
    return est(np.arange(ids.size)), np.std(boots, axis=0), int(ids.size)


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
        args = ["measure", config, "--out", out, "-j", str(processes), "--quiet"]
        if cli_main(args) != 0:
            raise ShearfitValueError(f"shearfit measure failed on {config}")
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
    (m1, m2, c1, c2), (sm1, sm2, sc1, sc2), n_pairs = _pair_bias(truths["plus"], truths["minus"], shear)
    summary = dict(out_dir=out_dir, input_shear=list(shear), recovered_shear=rec.tolist(),
                   recovered_shear_err=rec_err.tolist(), m=[m1, m2], m_err=[sm1, sm2], c=[c1, c2], c_err=[sc1, sc2],
                   n_galaxies=n_pairs, n_classified_galaxies=int(gal.sum()), n_stars_as_galaxies=n_star_as_gal,
                   psf=psf, seed=seed, wall_s=time.time() - t0, processes=processes)
    say("")
    say(f"input shear       g1 = {shear[0]:+.4f}            g2 = {shear[1]:+.4f}")
    say(f"recovered shear   g1 = {rec[0]:+.4f} +- {rec_err[0]:.4f}  g2 = {rec[1]:+.4f} +- {rec_err[1]:.4f}   "
        f"(weighted mean e of the {int(gal.sum())} objects classified as galaxies, {n_star_as_gal} of them "
        f"simulated stars; field +g)")
    say(f"multiplicative    m1 = {m1:+.4f} +- {sm1:.4f}   m2 = {m2:+.4f} +- {sm2:.4f}")
    say(f"additive          c1 = {c1:+.5f} +- {sc1:.5f} c2 = {c2:+.5f} +- {sc2:.5f}")
    say(f"   (raw, no noise-bias calibration; {n_pairs} simulated galaxies measured in both the +g and -g fields)")
    say(f"outputs: {out_dir}/field_plus and field_minus (exposures, field.yaml, truth.fits, shear.fits); "
        f"total {time.time() - t0:.0f} s on {processes} process(es)")
    return summary
