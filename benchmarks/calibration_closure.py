"""Closure of the noise-bias calibration (sec. 8.4) on simulated fields, and the second suite.

Simulates (``shearfit simulate``) and measures (``shearfit measure``) three sets of fields:

* calibration: ``--cal-seeds`` GREAT-like fields (the paper's population, 7 dithered exposures with
  elliptical Moffat PSFs, 2 CCDs), each twice with shear +g and -g from the same seed (same galaxies
  and noise), g of modulus ``--cal-g`` in a direction set by the seed;
* test: ``--test-seeds`` other seeds, other shears (modulus ``--test-g``), same construction; with
  ``--antithetic`` also each field's antithetic twin (``noise_sign: -1``: the same field with its
  pixel noise reversed), so that the additive bias c is measured free of the noise's odd part;
* second suite: ``--second-seeds`` fields of the second suite (Kolmogorov + optics, one exposure,
  random positions with overlaps), +g and -g;
* with ``--transfer-psf LO,HI`` (repeatable): the test set's first ``--transfer-seeds`` seeds again (the same
  galaxies, shears and pixel noise) with every exposure's PSF FWHM drawn from [LO, HI] arcsec instead: does the
  calibration carry to a survey of another seeing?

``--cal-extra-psf LO,HI`` adds ``--cal-extra-seeds`` more calibration seeds (from 1100) whose exposures' PSF FWHM
is drawn from [LO, HI] arcsec, so that the table spans a wider range of seeing; repeated, each range its own
seeds (the second from 1200, the third from 1300).

Then ``shearfit calibrate`` is fitted on the calibration set, applied to the test set and to the
second suite, and the script prints raw and calibrated m and c with bootstrap errors (over galaxies,
the +g and -g copies of a galaxy together), the fitted (alpha, beta) beside the paper's, and writes
``closure.png`` (raw and calibrated m against SNR and size, m against weight) and ``closure.json``.

Everything already simulated or measured under ``--out`` is reused, so the script resumes.

    python benchmarks/calibration_closure.py --out /tmp/closure -j 2
    python benchmarks/calibration_closure.py --out /tmp/closure -j 2 --antithetic --test-seeds 12
    python benchmarks/calibration_closure.py --out /tmp/closure -j 2 --size scalelength --transfer-psf 0.85,1.05
    python benchmarks/calibration_closure.py --out /tmp/closure -j 2 --cal-extra-psf 0.85,1.05 --cal-extra-seeds 10 \
        --cal-extra-psf 1.05,1.25 --seeing-bins 3 --transfer-psf 0.85,1.05 --transfer-psf 1.05,1.25 \
        --transfer-psf 1.25,1.45                                             # the package's default table

``--held-out-only`` simulates and measures only the held-out sets (test, second suite, transfer) and reports them
under the package's default calibration and the ``--compare`` files, whole and by the nearest catalogued neighbour,
with the galaxies' fitclass counts: how a pipeline change (``--set KEY=VALUE``) moves the shipped calibration's
closure, without refitting it::

    python benchmarks/calibration_closure.py --out /tmp/closure -j 2 --held-out-only --test-seeds 2
    python benchmarks/calibration_closure.py --out /tmp/closure -j 2 --held-out-only --test-seeds 2 \
        --set catalogue_blends=false

``--cross-validate`` fits the table again on the calibration set's even seeds and on its odd seeds (each seeing
range split alike) and applies each half's table to the other half's fields, whole and in bins of SNR: fields the
table was not fitted on but simulated exactly as it was, so that what the held-out sets leave can be told from the
table's own seed noise; and it prints how far the two halves' tables differ on the held-out sets, bin by bin (the
whole set's table carries about half of that).

``--size`` is the calibration table's size axis (``shearfit calibrate --size``): ``resolution``, the scalelength
over the catalogue's ``psf_fwhm`` (the default), or ``scalelength`` in arcsec.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import yaml

import shearfit
from shearfit.calib.calibrate import (PAPER_ALPHA, PAPER_BETA, CalibrationModel, calibrate, calibrated_bias,
                                      default_calibration, default_calibration_record, plot_calibration,
                                      quantity_bins, stack_matched, weight_bins, write_calibration)
from shearfit.app.cli import main as cli_main
from shearfit.simulate.field import simulate_missing

GREAT = dict(preset="small", ccd_nx=1024, ccd_ny=1024, grid_spacing=48.0, star_density=1.5)
SECOND = dict(preset="second-small", ccd_nx=1024, ccd_ny=1024, galaxy_density=40.0, star_density=10.0)


def shear_of(seed, modulus):
    """A shear of the given modulus in a direction fixed by the seed."""
    phi = np.random.default_rng(10_000 + seed).uniform(0, np.pi)
    return [modulus * np.cos(2 * phi), modulus * np.sin(2 * phi)]


def field_jobs(out, role, base, seeds, modulus, twins=False):
    """+g and -g fields of each seed; with ``twins`` also their antithetic twins (noise reversed, ``r``)."""
    jobs = []
    for seed in seeds:
        g = shear_of(seed, modulus)
        for noise_sign in ((1, -1) if twins else (1,)):
            for tag, sign in (("p", 1.0), ("m", -1.0)):
                cfg = dict(base, seed=int(seed), shear=[sign * g[0], sign * g[1]])
                if noise_sign < 0:
                    cfg["noise_sign"] = -1
                jobs.append((os.path.join(out, role, f"s{seed}{tag}" + ("r" if noise_sign < 0 else "")), cfg))
    return jobs


def measure(d, processes, psf, settings=(), tag=""):
    out = os.path.join(d, ("shear" if psf == "true" else "shear_fitted") + tag + ".fits")
    if not os.path.exists(out):
        config = os.path.join(d, "field_truepsf.yaml" if psf == "true" else "field.yaml")
        args = ["measure", config, *settings, "--out", out, "--quiet"]
        if processes > 1:
            args += ["-j", str(processes)]
        if cli_main(args) != 0:
            raise SystemExit(f"shearfit measure failed on {config}")
    return out, os.path.join(d, "truth.fits")


def nearest_neighbour(tab, pairs):
    """Each row's distance (arcsec) to the nearest other object of its field's input catalogue (the truth's
    galaxies and the field's stars), from the ``field`` index of :func:`stack_matched` into ``pairs``."""
    from scipy.spatial import cKDTree
    from astropy.table import Table

    out = np.full(len(tab), np.nan)
    field = np.asarray(tab["field"])
    for k, (_, truth) in enumerate(pairs):
        rows = np.nonzero(field == k)[0]
        if rows.size == 0:
            continue
        stars = os.path.join(os.path.dirname(truth), "stars.fits")
        cats = [Table.read(truth)] + ([Table.read(stars)] if os.path.exists(stars) else [])
        ra = np.concatenate([np.asarray(c["ra"], float) for c in cats])
        dec = np.concatenate([np.asarray(c["dec"], float) for c in cats])
        d0, r0 = np.radians(dec.mean()), np.radians(ra.mean())

        def xy(r, d):
            return np.c_[(np.radians(r) - r0) * np.cos(d0), np.radians(d) - d0] * 206264.806

        dist, _ = cKDTree(xy(ra, dec)).query(xy(np.asarray(tab["ra"], float)[rows], np.asarray(tab["dec"], float)[rows]), k=2)
        out[rows] = dist[:, 1]   # the first is the object itself
    return out


def held_out_report(role, pairs, calibrations, tag):
    """A held-out set alone under the given calibrations (the package's default, other files): m whole and split by
    the nearest catalogued neighbour, and how the pipeline classed the galaxies (+g fields) with and without a
    neighbour within 2"."""
    from astropy.table import Table, join

    tab = stack_matched(pairs)
    nn = nearest_neighbour(tab, pairs)
    print(f"\n{role} ({len(pairs) // 2} seeds, +g and -g; settings{tag.replace('_', ' ') or ' the defaults'})")
    print(f"{'':52s} {'n':>6s}  {'raw m':>18s}  {'calibrated m':>18s}")
    for cal in calibrations:
        name = os.path.basename(cal) if isinstance(cal, str) else "the package's default"
        for lo, hi in ((0, np.inf), (0, 2), (2, np.inf)):
            sel = (nn >= lo) & (nn < hi)
            if sel.sum() < 10:
                continue
            d = calibrated_bias(tab[sel], cal)
            print(f"{name[:32]:32s} neighbour {lo:g}-{hi:g}\" {d['n_galaxies']:6d}  {fmt(d, 'm_raw')}  "
                  f"{fmt(d, 'm_cal')}")
    counts = {}
    for k, (measured, truth) in enumerate(pairs):
        if not os.path.basename(os.path.dirname(measured)).endswith("p"):
            continue
        t = Table.read(truth)
        t = join(t[~np.asarray(t["is_star"], bool)]["id", "ra", "dec"], Table.read(measured)["id", "fitclass"], keys="id")
        t["field"] = k
        near = nearest_neighbour(t, pairs) < 2
        for close in (True, False):
            fc = np.asarray(t["fitclass"])[near == close]
            got = counts.setdefault(close, {})
            for code in np.unique(fc):
                got[int(code)] = got.get(int(code), 0) + int(np.sum(fc == code))
    for close, got in counts.items():
        print(f"galaxies {'with' if close else 'without'} a catalogued neighbour within 2\" (+g fields), by fitclass: "
              + ", ".join(f"{code}: {n}" for code, n in sorted(got.items())))


def both_bins(tab, column, calibration, n):
    """:func:`quantity_bins` with bootstrap errors over galaxies, and those over seeds beside them (``m_err_seeds``,
    ``m_cal_err_seeds``): each seed's fields have their own PSFs, whose scatter the galaxies' bootstrap misses."""
    out = quantity_bins(tab, column, calibration, n=n)
    by_seed = quantity_bins(tab, column, calibration, n=n, resample="seeds")
    out["m_err_seeds"] = by_seed["m_err"]
    out["m_cal_err_seeds"] = by_seed["m_cal_err"]
    return out


def binned_model(result, size):
    """The binned calibration (with its seeing tables) of a :func:`calibrate` result, as the package applies it."""
    return CalibrationModel(result["alpha"], result["beta"], "binned", result["binned"], size=size,
                            seeing=result.get("seeing"))


def seed_of(path):
    """The seed of a field's directory (``s1000p``, ``s2003mr``: 1000, 2003)."""
    return int(os.path.basename(os.path.dirname(path))[1:].rstrip("pmr"))


def cross_validation(cal_jobs, cal_pairs, held_out, args, n_bins=8):
    """The calibration fitted on the even and on the odd calibration seeds, each applied to the other half's
    fields (per seeing range, whole and in ``n_bins`` bins of SNR), and the two halves' tables on the held-out
    sets (``held_out``: {name: matched table}): their mean m per SNR bin and its difference."""
    halves = {}
    for parity, name in ((0, "even"), (1, "odd")):
        sel = [p for p in cal_pairs if seed_of(p[0]) % 2 == parity]
        res, _, _ = calibrate(sel, n_snr=args.n_snr, n_size=args.n_size, size=args.size, seeing_bins=args.seeing_bins,
                              n_boot=4)
        halves[name] = (binned_model(res, args.size), parity)
    roles = {}
    for (d, _), p in zip(cal_jobs, cal_pairs):
        roles.setdefault(os.path.basename(os.path.dirname(d)), []).append(p)
    print(f"\ncross-validation: the table fitted on the calibration set's even seeds applied to its odd seeds, and the "
          f"odd seeds' to the even ones; calibrated m whole and in {n_bins} bins of SNR (bootstrap over galaxies, "
          "[over seeds])")
    for name, (model, parity) in halves.items():
        for role, ps in roles.items():
            other = [p for p in ps if seed_of(p[0]) % 2 != parity]
            if not other:
                continue
            tab = stack_matched(other)
            d = calibrated_bias(tab, model, n_boot=100)
            ds = calibrated_bias(tab, model, n_boot=100, resample="seeds")
            q = both_bins(tab, "snr", model, n_bins)
            print(f"  {name} -> other, {role:22s} {d['n_galaxies']:6d}  m {fmt(d, 'm_cal')} [{ds['m_cal_err']:.4f}];  "
                  "SNR " + " ".join(f"{r['x']:.0f}: {r['m_cal']:+.3f}" for r in q)
                  + f"  (faintest +- {q['m_cal_err'][0]:.3f} [{q['m_cal_err_seeds'][0]:.3f}])")
    print("  the halves' tables on the held-out sets, per bin of SNR: SNR, mean m (even), mean m (odd), difference")
    for role, tab in held_out.items():
        qe = quantity_bins(tab, "snr", halves["even"][0], n=n_bins, n_boot=2)
        qo = quantity_bins(tab, "snr", halves["odd"][0], n=n_bins, n_boot=2)
        print(f"  {role:24s} " + "  ".join(f"{a['x']:.0f}: {a['m_pred']:+.3f} {b['m_pred']:+.3f} "
                                           f"({a['m_pred'] - b['m_pred']:+.3f})" for a, b in zip(qe, qo)))


def fmt(d, k, scale=1.0):
    return f"{d[k] * scale:+.4f} +- {d[k + '_err'] * scale:.4f}"


def plot(path, cal_result, bins, test_snr, test_size, test_weight, second_snr):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    for a, tb, lab, log in ((ax[0], test_snr, "SNR", True), (ax[1], test_size, "scalelength (arcsec)", False)):
        x = np.asarray(tb["snr" if lab == "SNR" else "r"])
        a.errorbar(x, tb["m"], tb["m_err"], fmt="o", ms=4, label="test set, raw")
        a.errorbar(x * 1.02, tb["m_cal"], tb["m_cal_err"], fmt="s", ms=4, label="test set, calibrated")
        a.plot(x, tb["m_pred"], "-", lw=1, label="calibration <m> (binned)")
        if lab == "SNR" and second_snr is not None:
            xs = np.asarray(second_snr["snr"])
            a.errorbar(xs * 0.98, second_snr["m_cal"], second_snr["m_cal_err"], fmt="^", ms=4,
                       label="second suite, calibrated")
        a.axhline(0, color="k", lw=0.5)
        a.set_xlabel(lab)
        a.set_ylabel("m")
        if log:
            a.set_xscale("log")
        a.legend(fontsize=7)
    wb = test_weight
    ax[2].errorbar(wb["weight"], wb["m"], wb["m_err"], fmt="o", ms=4, label="test set, raw")
    ax[2].errorbar(wb["weight"], wb["m_cal"], wb["m_cal_err"], fmt="s", ms=4, label="test set, calibrated")
    ax[2].plot(wb["weight"], wb["m_pred"], "-", lw=1, label="calibration <m> (binned)")
    ax[2].axhline(0, color="k", lw=0.5)
    ax[2].set_xlabel("mean lensfit weight")
    ax[2].set_ylabel("m")
    ax[2].legend(fontsize=7)
    fig.suptitle(f"calibration alpha = {cal_result['alpha']:.3f} +- {cal_result['alpha_err']:.3f}, beta = "
                 f"{cal_result['beta']:.3f} +- {cal_result['beta_err']:.3f} (paper 0.057, -0.37)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--cal-seeds", type=int, default=10)
    ap.add_argument("--test-seeds", type=int, default=6)
    ap.add_argument("--second-seeds", type=int, default=4)
    ap.add_argument("--cal-g", type=float, default=0.04)
    ap.add_argument("--test-g", type=float, default=0.05)
    ap.add_argument("--psf", choices=["true", "fitted"], default="true",
                    help="measure with the true PSF given (default) or with PSF models fitted from the stars")
    ap.add_argument("--ccd", type=int, default=1024, help="CCD side in pixels (2 CCDs per field)")
    ap.add_argument("--n-snr", type=int, default=20)
    ap.add_argument("--n-size", type=int, default=20)
    ap.add_argument("--antithetic", action="store_true",
                    help="add the test set's antithetic twins (the same fields with the pixel noise reversed): "
                         "the noise's odd part cancels in c, which the +g / -g pairs do not free of it")
    ap.add_argument("-j", "--processes", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of shearfit measure for every field (e.g. size_prior_axis=area); the fields are "
                         "shared between settings, each measured once per distinct set of them")
    ap.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                    help="a simulation key for the GREAT-like fields (calibration and test sets), e.g. "
                         "psf_variation=0; give another --out, since the fields there are reused as they are")
    ap.add_argument("--size", choices=["resolution", "scalelength"], default="resolution",
                    help="the calibration table's size axis (shearfit calibrate --size)")
    ap.add_argument("--transfer-psf", action="append", default=[], metavar="LO,HI",
                    help="also measure the first --transfer-seeds test seeds with every exposure's PSF FWHM drawn "
                         "from [LO, HI] arcsec (the GREAT-like fields draw 0.55-0.85), and apply the calibration "
                         "(repeatable)")
    ap.add_argument("--cal-extra-psf", action="append", default=[], metavar="LO,HI",
                    help="add --cal-extra-seeds calibration seeds (1100, 1101, ...) with every exposure's PSF FWHM "
                         "drawn from [LO, HI] arcsec (repeatable: the k-th range's seeds from 1100 + 100 k)")
    ap.add_argument("--cal-extra-seeds", type=int, default=0)
    ap.add_argument("--seeing-bins", type=int, default=1,
                    help="also fit a table per range of the PSF's FWHM, this many ranges (shearfit calibrate "
                         "--seeing-bins), which the calibration applies")
    ap.add_argument("--transfer-seeds", type=int, default=4,
                    help="test seeds (2000, 2001, ...) each --transfer-psf set simulates again")
    ap.add_argument("--compare", action="append", default=[], metavar="CALIBRATION.yaml",
                    help="also apply this calibration file to the test set, the second suite and the transfer sets "
                         "(e.g. an earlier default: git show REV:src/shearfit/calib/default_calibration.yaml > F)")
    ap.add_argument("--write-default", default=None, metavar="PATH",
                    help="also write the calibration set's binned calibration, with this run's closure on the test "
                         "set and the second suite, as the package's default (src/shearfit/calib/"
                         "default_calibration.yaml)")
    ap.add_argument("--cross-validate", action="store_true",
                    help="also fit the table on the calibration set's even and odd seeds and apply each to the other "
                         "half (the table's own seed noise, against which the held-out residuals are read)")
    ap.add_argument("--held-out-only", action="store_true",
                    help="simulate and measure only the test set, the second suite and the --transfer-psf sets, and "
                         "report them under the package's default calibration and the --compare files, by nearest "
                         "catalogued neighbour and fitclass (a pipeline change against the shipped calibration)")
    args = ap.parse_args(argv)
    tag = "".join("_" + "".join(ch if ch.isalnum() else "-" for ch in item) for item in args.set)
    # the catalogues (measured once per setting) do not depend on the size axis; the calibration's files do
    ctag = tag + ("_size-scalelength" if args.size == "scalelength" else "") + (
        "".join(f"_cal-psf-{item.replace(',', '-')}-x{args.cal_extra_seeds}" for item in args.cal_extra_psf)
        if args.cal_extra_seeds > 0 else "") + (
        f"_seeing-{args.seeing_bins}" if args.seeing_bins > 1 else "")
    out = os.path.abspath(args.out)
    t0 = time.time()
    great = dict(GREAT, ccd_nx=args.ccd, ccd_ny=args.ccd)
    for kv in args.sim:
        k, v = kv.split("=", 1)
        great[k.strip()] = yaml.safe_load(v)
    second = dict(SECOND, ccd_nx=args.ccd, ccd_ny=args.ccd)
    sets = dict(cal=field_jobs(out, "cal", great, range(1000, 1000 + args.cal_seeds), args.cal_g),
                test=field_jobs(out, "test", great, range(2000, 2000 + args.test_seeds), args.test_g,
                                twins=args.antithetic),
                second=field_jobs(out, "second", second, range(3000, 3000 + args.second_seeds), args.test_g))
    for k, item in enumerate(args.cal_extra_psf if args.cal_extra_seeds > 0 else []):
        lo_hi = [float(v) for v in item.split(",")]
        first = 1100 + 100 * k
        sets["cal"] += field_jobs(out, f"cal-psf-{lo_hi[0]:g}-{lo_hi[1]:g}", dict(great, psf_fwhm_range=lo_hi),
                                  range(first, first + args.cal_extra_seeds), args.cal_g)
    for item in args.transfer_psf:
        lo_hi = [float(v) for v in item.split(",")]
        tdir = f"transfer-psf-{lo_hi[0]:g}-{lo_hi[1]:g}"
        sets[tdir] = field_jobs(out, tdir, dict(great, psf_fwhm_range=lo_hi), range(2000, 2000 + args.transfer_seeds),
                                args.test_g)
    if args.held_out_only:
        del sets["cal"]
    jobs = [j for v in sets.values() for j in v]
    with ProcessPoolExecutor(args.processes) as pool:
        list(pool.map(simulate_missing, jobs))
    print(f"simulated {len(jobs)} fields in {time.time() - t0:.0f} s", flush=True)
    pairs = {}
    for role, js in sets.items():
        pairs[role] = []
        for d, _ in js:
            ts = time.time()
            pairs[role].append(measure(d, args.processes, args.psf, args.set, tag))
            print(f"  measured {d} in {time.time() - ts:.0f} s", flush=True)
    t_meas = time.time() - t0
    # the package's default for these settings (its self-calibration table where the settings ask for it)
    selfcal = any(k.strip() == "self_calibration" and yaml.safe_load(v) is True
                  for k, v in (item.split("=", 1) for item in args.set))
    package_default = default_calibration(self_calibration=selfcal)
    if args.held_out_only:
        for role, ps in pairs.items():
            if ps:
                held_out_report(role, ps, [package_default, *args.compare], tag)
        print(f"\n{time.time() - t0:.0f} s in all ({t_meas:.0f} s simulating and measuring)")
        return 0

    result, bins, cal_tab = calibrate(pairs["cal"], n_snr=args.n_snr, n_size=args.n_size, size=args.size,
                                      seeing_bins=args.seeing_bins)
    write_calibration(result, os.path.join(out, f"calibration{ctag}.yaml"))
    a, b = result["alpha"], result["beta"]
    binned = binned_model(result, args.size)
    fitted = CalibrationModel(a, b)
    paper = CalibrationModel(PAPER_ALPHA, PAPER_BETA)
    plot_calibration(bins, result, os.path.join(out, f"calibration{ctag}.png"), weight_bins=weight_bins(cal_tab, binned))
    test = stack_matched(pairs["test"])
    second = stack_matched(pairs["second"])
    # a table in resolution needs the catalogues' psf_fwhm, which those measured before 2026-11-26 lack
    def defaults(tab):
        return [] if package_default.size == "resolution" and "psf_fwhm" not in tab.colnames else [package_default]

    transfer = {role: stack_matched(pairs[role]) for role in pairs if role.startswith("transfer")}
    for t in (test, *transfer.values()):
        if "psf_fwhm" in t.colnames:   # catalogues measured before 2026-11-26 have none
            t["resolution"] = np.asarray(t["scalelength"], float) / np.asarray(t["psf_fwhm"], float)
    rows = [("calibration set (self), binned", calibrated_bias(cal_tab, binned)),
            ("calibration set (self), fitted form", calibrated_bias(cal_tab, fitted)),
            ("test set, binned", calibrated_bias(test, binned)),
            ("test set, fitted form", calibrated_bias(test, fitted)),
            ("test set, paper's alpha, beta", calibrated_bias(test, paper)),
            *[("test set, the package's default", calibrated_bias(test, default)) for default in defaults(test)],
            *([("test set, noise sign +1 only, binned",
                calibrated_bias(stack_matched([p for (d, _), p in zip(sets["test"], pairs["test"])
                                               if not d.endswith("r")]), binned))] if args.antithetic else []),
            ("second suite, binned", calibrated_bias(second, binned)),
            ("second suite, fitted form", calibrated_bias(second, fitted)),
            ("second suite, paper's alpha, beta", calibrated_bias(second, paper)),
            *[("second suite, the package's default", calibrated_bias(second, default)) for default in defaults(second)],
            *[(f"{name}, {os.path.basename(path)}", calibrated_bias(tab, path)) for path in args.compare
              for name, tab in (("test set", test), ("second suite", second), *transfer.items())],
            *[row for role, tab in transfer.items() for row in (
                (f"{role} ({len(pairs[role]) // 2} test seeds), binned", calibrated_bias(tab, binned)),
                *[(f"{role}, the package's default", calibrated_bias(tab, default)) for default in defaults(tab)])],
            # the transfer sets' seeds at the test set's seeing (the same galaxies and noise)
            *[(f"test seeds 2000-{1999 + args.transfer_seeds} at the test set's seeing, binned",
               calibrated_bias(test[np.asarray(test["group"]) // 10 ** 8 < 2000 + args.transfer_seeds], binned))
              for _ in [0] if transfer]]
    # the second suite's galaxies lie at random positions: split by the distance to the nearest catalogued neighbour
    nn = nearest_neighbour(second, pairs["second"])
    for lo, hi in ((0, 2), (2, np.inf)):
        sel = (nn >= lo) & (nn < hi)
        if sel.sum() > 10:
            rows.append((f"second suite, nearest neighbour {lo:g}-{hi:g}\", binned", calibrated_bias(second[sel], binned)))
    t_snr = both_bins(test, "snr", binned, 6)
    t_size = both_bins(test, "scalelength", binned, 6)
    extra = [("test set in bins of resolution (scalelength / psf_fwhm)", both_bins(test, "resolution", binned, 6),
              "x", "7.3f")] if "resolution" in test.colnames else []
    for role, tab in transfer.items():
        extra += [(f"{role} in bins of resolution", both_bins(tab, "resolution", binned, 6), "x", "7.3f"),
                  (f"{role} in bins of SNR", both_bins(tab, "snr", binned, 6), "snr", "7.1f")]
    t_w = weight_bins(test, binned, n=8)
    s_snr = both_bins(second, "snr", binned, 4)
    plot(os.path.join(out, f"closure{ctag}.png"), result, bins, t_snr, t_size, t_w, s_snr)

    print()
    print(f"calibration set: {result['n_galaxies']} galaxy measurements ({result['n_groups']} galaxies, "
          f"{len(pairs['cal'])} fields), {result['n_snr_bins']} x {result['n_size_bins']} bins")
    print(f"  alpha = {a:.4f} +- {result['alpha_err']:.4f}   beta = {b:.4f} +- {result['beta_err']:.4f}   "
          f"(paper {PAPER_ALPHA}, {PAPER_BETA});  chi2 = {result['chi2']:.1f} for {result['dof']} dof")
    print(f"{'':52s} {'n':>6s}  {'raw m':>18s}  {'<m(nu,r)>':>9s}  {'calibrated m':>18s}  "
          f"{'c1':>20s}  {'c2':>20s}")
    for name, d in rows:
        print(f"{name:52s} {d['n_galaxies']:6d}  {fmt(d, 'm_raw')}  {d['m_mean']:+9.4f}  {fmt(d, 'm_cal')}  "
              f"{fmt(d, 'c1')}  {fmt(d, 'c2')}")
    # Each field has its own seven PSFs, and m varies from field to field by more than its galaxies' noise: the
    # bootstrap over galaxies above does not see that; the scatter of the seeds' m does.
    for role, tab in (("calibration set", cal_tab), ("test set", test), *transfer.items()):
        seed = np.asarray(tab["group"]) // 10 ** 8          # matched_galaxies: group = SEED * 10^8 + id
        per = np.array([[calibrated_bias(tab[seed == s], binned, n_boot=2)[k] for k in ("m_raw", "m_cal")]
                        for s in np.unique(seed)])
        if len(per) > 1:
            sem = per.std(axis=0, ddof=1) / np.sqrt(len(per))
            print(f"{role} per seed, raw m: {' '.join(f'{v:+.3f}' for v in per[:, 0])}; mean {per[:, 0].mean():+.4f} "
                  f"+- {sem[0]:.4f} (scatter of {len(per)} seeds); calibrated: mean {per[:, 1].mean():+.4f} +- "
                  f"{sem[1]:.4f}")
    for title, tb, key, f in (("test set in bins of SNR", t_snr, "snr", "7.1f"),
                              ("test set in bins of scalelength", t_size, "r", "7.3f"),
                              ("test set in bins of weight", t_w, "weight", "7.2f"),
                              ("second suite in bins of SNR", s_snr, "snr", "7.1f"), *extra):
        seeds = "m_cal_err_seeds" in tb.colnames
        print(f"\n{title}: {key}, raw m, <m(nu,r)>, calibrated m (errors: bootstrap over galaxies"
              + (", [over seeds])" if seeds else ")"))
        for r in tb:
            print(f"  {r[key]:{f}}  {r['m']:+.4f} +- {r['m_err']:.4f}" + (f" [{r['m_err_seeds']:.4f}]" if seeds else "")
                  + f"  {r['m_pred']:+.4f}  {r['m_cal']:+.4f} +- {r['m_cal_err']:.4f}"
                  + (f" [{r['m_cal_err_seeds']:.4f}]" if seeds else ""))
    summary = dict(alpha=a, beta=b, alpha_err=result["alpha_err"], beta_err=result["beta_err"],
                   chi2=result["chi2"], dof=result["dof"], rows={name: d for name, d in rows},
                   measure_wall_s=t_meas, total_wall_s=time.time() - t0, processes=args.processes, psf=args.psf)
    with open(os.path.join(out, f"closure{ctag}.json"), "w") as f:
        json.dump(summary, f, indent=1)
    if args.cross_validate:
        cross_validation(sets["cal"], pairs["cal"], {"test set": test, **transfer}, args)
    if args.write_default:
        command = "python benchmarks/calibration_closure.py " + " ".join(sys.argv[1:] if argv is None else argv)
        closure = {name: {k: float(d[k]) for k in ("m_raw", "m_raw_err", "m_cal", "m_cal_err")} | {
            "n_galaxies": int(d["n_galaxies"])} for name, d in rows if "binned" in name}
        record = default_calibration_record(
            result, f"{command} (shearfit {shearfit.__version__}; fields {args.cal_seeds} calibration"
                    + "".join(f" and {args.cal_extra_seeds} more with PSF FWHM {item}" for item in args.cal_extra_psf
                              if args.cal_extra_seeds > 0)
                    + ", "
                    f"{args.test_seeds} test, {args.second_seeds} second-suite seeds; PSF {args.psf}; settings "
                    f"{' '.join(args.set) or 'the defaults'})", closure)
        write_calibration(record, args.write_default)
        print(f"written the default calibration {args.write_default}")
    print(f"\nwritten {out}/calibration{ctag}.yaml, calibration{ctag}.png, closure{ctag}.png, closure{ctag}.json; "
          f"{time.time() - t0:.0f} s in all ({t_meas:.0f} s simulating and measuring)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
