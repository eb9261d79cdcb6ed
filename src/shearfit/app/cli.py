"""The ``shearfit`` command: parses arguments, calls the library, reports.

``main(argv)`` returns the exit status, so tests call it without a
subprocess. Errors from bad input are one line on stderr and a non-zero
status; nothing else of the library prints unless asked to.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np

from ..version import __version__
from ..errors import ShearfitError, ShearfitValueError

__all__ = ["main"]


def _add_common(p):
    p.add_argument("-v", "--verbosity", type=int, default=1, choices=range(0, 4),
                   help="0 quiet, 1 normal, 2 progress details, 3 debug")
    p.add_argument("-l", "--log-file", default=None, help="also write the log to this file")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no report")


def _cmd_demo(args):
    if args.stamps:
        from .demo_stamps import run_demo

        kwargs = {} if args.n_galaxies is None else {"n_galaxies": args.n_galaxies}
        run_demo(out_dir=args.out, processes=args.processes, seed=args.seed, quiet=args.quiet, **kwargs)
        return 0
    from .demo import run_field_demo

    run_field_demo(out_dir=args.out, processes=args.processes, seed=args.seed, quiet=args.quiet, psf=args.psf)
    return 0


def _cmd_measure(args):
    from ..io.fieldconfig import load_field_config
    from ..pipeline.driver import measure_field

    cfg = load_field_config(args.config, overrides=args.overrides)
    table = measure_field(cfg, out_path=args.out, progress=not args.quiet and sys.stderr.isatty(),
                          processes=args.processes, restart=args.restart, scheduler=args.scheduler,
                          executor=args.executor, memory_limit=args.memory_limit)
    if not args.quiet:
        fc = table["fitclass"]
        print(f"measured {len(table)} objects: {int((fc == 0).sum())} galaxies, {int((fc == 1).sum())} stars, "
              f"{int((fc < 0).sum())} not measured; catalogue: {args.out or cfg.output}")
    return 0


def _cmd_systematics(args):
    from ..stats.systematics import run_systematics

    if args.n_bins < 1:
        raise ShearfitError("--n-bins must be at least 1")
    tables = run_systematics(args.catalogs, args.out, truth=args.truth, n_bins=args.n_bins, seed=args.seed)
    if not args.quiet:
        t = tables["PSFGAL_SNR"]
        t = t[t["field"] == "all"]
        print(f"PSF-galaxy cross-correlation <e . e_psf> against SNR ({args.out}/systematics.fits, PNG plots):")
        for row in t:
            print(f"  SNR {row['lo']:7.1f}-{row['hi']:7.1f}: {row['xi_psf_gal']:+.2e} +/- {row['xi_err']:.1e} "
                  f"({row['n']} galaxies)")
    return 0


def _cmd_xipm(args):
    from ..stats.twopoint import (bin_pairs, measured, metacal_response_of, parse_bins, parse_selection, plot_xipm,
                                  read_shear_catalog, split_bins, write_xipm_file, xipm_bins)

    if not (0 < args.min_sep < args.max_sep) or args.nbins < 1:
        raise ShearfitError("--min-sep must be positive and below --max-sep, --nbins at least 1")
    if args.bin_slop < 0 or args.angle_slop < 0:
        raise ShearfitError("--bin-slop and --angle-slop must be at least 0")
    if args.patches and args.patches < 2:
        raise ShearfitError(f"--patches {args.patches}: a jackknife needs at least 2 patches")
    if args.plot is not None and not args.plot.lower().endswith(".png"):
        raise ShearfitError(f"--plot {args.plot}: expected a .png file name")
    sel = [parse_selection(t) for t in args.select]
    spec = parse_bins(args.bins) if args.bins is not None else None
    full = read_shear_catalog(args.catalog, sel, measured_only=False, weight_column=args.weight_column)
    if spec is not None:
        col, edges = spec
        fulls = split_bins(full, col, edges, args.catalog)
        names = [f"bin {k} ({col} {lo:g}-{hi:g})" for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:]))]
    else:
        fulls, names = [full], ["the selected catalogue"]
    tabs = [measured(f) for f in fulls]
    Rs = [metacal_response_of(f, args.catalog) if args.calibration is None else None for f in fulls]
    results, cov, jk = xipm_bins(tabs, args.min_sep, args.max_sep, args.nbins, calibration=args.calibration,
                                 n_sys=args.n_sys, seed=args.seed, bin_slop=args.bin_slop, responses=Rs,
                                 npatch=args.patches or 0, names=names, angle_slop=args.angle_slop)
    metacal = any(R is not None for R in Rs)
    calib = args.calibration or ("metacal response" if metacal else "catalogue m column")
    common = [("CALIB", calib, "calibration used"),
              ("BINSLOP", float(args.bin_slop), "TreeCorr bin_slop (0: exact pair binning)"),
              ("ANGSLOP", float(args.angle_slop), "TreeCorr angle_slop (rad)"),
              ("WEIGHTS", args.weight_column, "the catalogue's column of weights")]
    common += [(f"SELECT{i}", t, "selection") for i, t in enumerate(args.select)]
    if args.patches:
        common += [("NPATCH", int(args.patches), "jackknife patches (k-means, seeded by SEED)"),
                   ("SEED", int(args.seed), "random seed (patches, calibration draws)")]

    def mcr(prefix, R, what):
        return [] if R is None else [(f"{prefix}{a + 1}{b + 1}", float(R[a][b]), f"metacal response{what}")
                                     for a in range(2) for b in range(2)]

    if spec is None:
        hdu_names = ["XIPM"]
        cards = [[("NGAL", len(tabs[0]), "galaxies used")] + common[:1] + mcr("MCR", Rs[0], " (shear + selection)")
                 + common[1:]]
        labels = {(0, 0): "all galaxies"}
        primary = []
    else:
        col, edges = spec
        hdu_names, cards, labels = [], [], {}
        for i, j in bin_pairs(len(tabs)):
            hdu_names.append(f"XIPM_{i}_{j}")
            c = [("PAIR", f"{i}_{j}", "pair of bins (i, j)"), ("BIN1", i, "first bin"), ("BIN2", j, "second bin"),
                 ("BINCOL", col, "catalogue column of the bins (lo <= value < hi)")]
            for key, k in (("1", i), ("2", j)):
                c += [(f"BIN{key}LO", float(edges[k]), f"bin {k} lower edge"),
                      (f"BIN{key}HI", float(edges[k + 1]), f"bin {k} upper edge"),
                      (f"NGAL{key}", len(tabs[k]), f"galaxies in bin {k}")]
            c += common[:1] + mcr("MCRA", Rs[i], f" of bin {i}") + mcr("MCRB", Rs[j], f" of bin {j}") + common[1:]
            cards.append(c)
            labels[(i, j)] = f"{col} [{edges[i]:g},{edges[i + 1]:g}) x [{edges[j]:g},{edges[j + 1]:g})"
        primary = [("BINCOL", col, "catalogue column of the tomographic bins"), ("NTOMO", len(tabs), "bins"),
                   ("BINS", args.bins, "--bins")]
        primary += [(f"EDGE{k}", float(e), "bin edge") for k, e in enumerate(edges)]
        primary += [(f"NGAL{k}", len(t), f"galaxies in bin {k}") for k, t in enumerate(tabs)]
    cov_cards = [("NPATCH", int(args.patches or 0), "jackknife patches"),
                 ("CPWEIGHT", "match", "TreeCorr cross_patch_weight")]
    write_xipm_file(args.out, [t for _, t in results], hdu_names, cards, syscov=cov, jkcov=jk,
                    pairs=[p for p, _ in results], nbins=args.nbins, cov_cards=cov_cards, primary_cards=primary)
    if args.plot is not None:
        plot_xipm(results, args.plot, labels=labels, title=args.catalog)
    if not args.quiet:
        extra = [" (with the systematic covariance)" if cov is not None else "",
                 f" (jackknife covariance over {args.patches} patches: HDU COV)" if jk is not None else ""]
        ngal = sum(len(t) for t in tabs)
        what = f" in {len(tabs)} bins of {spec[0]}, {len(results)} pairs" if spec is not None else ""
        print(f"xi+/xi- of {ngal} galaxies{what}, {args.nbins} angular bins, {args.min_sep}-{args.max_sep} arcmin: "
              f"{args.out}" + "".join(extra) + (f"; plot {args.plot}" if args.plot else ""))
        jkcol = jk is not None
        for (i, j), table in results:
            if spec is not None:
                print(f" {hdu_names[bin_pairs(len(tabs)).index((i, j))]}: {labels[(i, j)]}, "
                      f"{len(tabs[i])} x {len(tabs[j])} galaxies")
            for row in table:
                if row["npairs"] == 0:
                    # a bin wider than the field: kept in the file (NaN), named here rather than printed as NaN
                    print(f"  theta {row['theta']:8.3f}'  no pairs (the catalogue spans less than this)")
                    continue
                jp = f" (jk {row['sigma_xip_jk']:.1e})" if jkcol else ""
                jm = f" (jk {row['sigma_xim_jk']:.1e})" if jkcol else ""
                print(f"  theta {row['theta']:8.3f}'  xi+ {row['xip']:+.3e} +/- {row['sigma_xip']:.1e}{jp}  "
                      f"xi- {row['xim']:+.3e} +/- {row['sigma_xim']:.1e}{jm}  1+K {row['one_plus_k']:.4f}  "
                      f"pairs {row['npairs']:.0f}")
    return 0


def _cmd_noisebias(args):
    import io

    from ..calib.noisebias import run_noisebias

    if args.pairs < 10:
        raise ShearfitError(f"--pairs must be at least 10 (got {args.pairs})")
    run_noisebias(args.out, snr_mc=tuple(args.snr), n_pairs=args.pairs, seed=args.seed,
                  stream=io.StringIO() if args.quiet else None)
    return 0


def _cmd_psf(args):
    import os

    from astropy.table import Table

    from ..io.fieldconfig import load_field_config
    from ..io.fits import read_catalog, read_exposure
    from ..pipeline.driver import fit_exposure_psf, star_catalogue_positions
    from ..psf.build import write_psf_model
    from ..psf.diagnostics import psf_diagnostics, write_diagnostics
    from ..workers import single_threaded

    cfg = load_field_config(args.config, overrides=args.overrides)
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(args.config)), "psf")
    os.makedirs(out, exist_ok=True)
    cat = read_catalog(cfg.catalog)
    stars = star_catalogue_positions(cfg)   # read once for all the exposures
    summary = []
    # one BLAS thread, as in shearfit measure: the star fits' small products gain no wall time from more
    with single_threaded():
        for k, spec in enumerate(cfg.exposures):
            ccds = read_exposure(spec.image, spec.weight)
            stem = os.path.splitext(os.path.basename(spec.image))[0]
            res = fit_exposure_psf(cfg, cat, ccds, f"exposure {k} ({spec.image})", stars)
            prefix = os.path.join(out, stem)
            write_psf_model(res.model, f"{prefix}.psfmodel.fits")
            diag = psf_diagnostics(res, ccds, n_bootstrap=0 if args.no_bootstrap else cfg.pipeline.psf_bootstrap,
                                   pc=cfg.pipeline)
            paths = write_diagnostics(diag, res, prefix)
            g = diag["grid"]
            summary.append(dict(exposure=k, image=spec.image, model=f"{prefix}.psfmodel.fits", n_stars=len(res.stars),
                                ccds_used=int(res.model.ccd_used.sum()), n_ccd=len(ccds),
                                mean_e1=float(np.nanmean(g["e1"])), mean_e2=float(np.nanmean(g["e2"])),
                                rms_offset=float(np.sqrt(np.mean(res.info["offset"] ** 2)))))
            if not args.quiet:
                print(f"exposure {k}: {len(res.stars)} stars on {int(res.model.ccd_used.sum())}/{len(ccds)} CCDs; "
                      f"model {prefix}.psfmodel.fits; diagnostics {', '.join(paths)}")
                for note in res.notes:
                    print(f"  {note}")
    Table(rows=[tuple(s.values()) for s in summary], names=list(summary[0].keys())).write(
        os.path.join(out, "psf_summary.fits"), overwrite=True)
    return 0


def _cmd_simulate(args):
    from ..files import read_yaml_mapping
    from ..simulate.field import simulate_field, simulation_config

    mapping = read_yaml_mapping(args.config, "simulation config")
    if args.seed is not None:
        mapping["seed"] = args.seed
    sc = simulation_config(mapping)
    res = simulate_field(sc, args.out)
    if not args.quiet:
        print(f"simulated {sc.suite} field (preset {sc.preset}, seed {sc.seed}): {res['n_galaxies']} galaxies, "
              f"{res['n_stars']} stars, {sc.n_exposures} exposures x {sc.n_ccd} CCDs, pixel noise {res['sigma']:.3g}; "
              f"config {res['config']}, truth {res['truth']}")
    return 0


def _cmd_calibrate(args):
    import os

    from ..calib.calibrate import CalibrationModel, calibrate, plot_calibration, weight_bins, write_calibration
    from ..io.fits import write_catalog_atomic

    files = [args.measured, args.truth] + list(args.more)
    if len(files) % 2:
        raise ShearfitValueError(f"calibrate takes MEASURED TRUTH pairs; {files[-1]} has no partner")
    pairs = list(zip(files[0::2], files[1::2]))
    result, bins, tab = calibrate(pairs, n_snr=args.n_snr, n_size=args.n_size, n_boot=args.bootstrap,
                                  seed=args.seed, model=args.model, size=args.size, seeing_bins=args.seeing_bins)
    write_calibration(result, args.out)
    stem = os.path.splitext(args.out)[0]
    write_catalog_atomic(bins, f"{stem}_bins.fits", [])
    wb = weight_bins(tab, CalibrationModel(result["alpha"], result["beta"], result["model"], result["binned"],
                                           size=result["size"], seeing=result.get("seeing")))
    plot_calibration(bins, result, f"{stem}.png", weight_bins=wb)
    if not args.quiet:
        print(f"calibration from {result['n_galaxies']} galaxies in {result['n_snr_bins']} x {result['n_size_bins']} "
              f"bins: alpha = {result['alpha']:.4f} +- {result['alpha_err']:.4f}, beta = {result['beta']:.3f} +- "
              f"{result['beta_err']:.3f} (paper 0.057, -0.37); overall raw m = {result['m_raw']:+.4f}, "
              f"c = ({result['c1']:+.5f}, {result['c2']:+.5f}); written {args.out}, {stem}_bins.fits, {stem}.png")
    return 0


def build_parser():
    parser = argparse.ArgumentParser(
        prog="shearfit",
        description="Bayesian bulge+disk shear measurement on individual exposures (lensfit, Miller et al. 2013).")
    parser.add_argument("--version", action="version", version=f"shearfit {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("demo", help="simulate a small field with a known shear, run the pipeline, print m and c",
                       description="Simulate a small CFHTLenS-like field twice (shear +g and -g; 2 CCDs, 7 dithered "
                                   "exposures with elliptical Moffat PSFs, stars), fit the PSF models from the "
                                   "stars, measure every object and print the input and recovered shear with the "
                                   "multiplicative and additive bias. --stamps runs the single-object engine on "
                                   "GalSim postage stamps instead.")
    p.add_argument("--out", default=None, help="output directory (default: ./shearfit_demo)")
    p.add_argument("--psf", choices=["fitted", "true"], default="fitted",
                   help="PSF models fitted from the stars (default) or the true PSF given")
    p.add_argument("--stamps", action="store_true", help="the postage-stamp ring demo of the engine alone")
    p.add_argument("--n-galaxies", type=int, default=None, help="(--stamps) galaxies, each at several orientations")
    p.add_argument("--processes", type=int, default=None, help="worker processes (default: all cores)")
    p.add_argument("--seed", type=int, default=1, help="random seed")
    _add_common(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("measure", help="measure the shear of every catalogue object on a field's exposures",
                       description="PSF models (given), stamps, joint fits over exposures, shear catalogue.")
    p.add_argument("config", help="the field's YAML config (docs/interface.rst)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="settings that override the config's")
    p.add_argument("--out", default=None, help="output catalogue (default: the config's output:)")
    p.add_argument("-j", "--processes", type=int, default=1,
                   help="worker processes (a local Dask cluster of that many workers when more than 1)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on an existing Dask distributed scheduler (e.g. tcp://host:8786; dask-jobqueue "
                        "clusters serve one); its workers must see the same files")
    p.add_argument("--executor", choices=["dask", "processes", "fork"], default="dask",
                   help="with -j N: a local Dask cluster (default) or a plain process pool ('processes'; "
                        "'fork' is its old name: fork on Linux, spawn elsewhere)")
    p.add_argument("--memory-limit", default="auto", metavar="SIZE",
                   help="memory per worker of the local Dask cluster (e.g. 2GB; Dask pauses, then restarts, a "
                        "worker above it; default auto: the machine's memory shared by the workers)")
    p.add_argument("--restart", action="store_true",
                   help="discard the checkpoint (OUTPUT.parts/) of an interrupted run instead of resuming it")
    _add_common(p)
    p.set_defaults(func=_cmd_measure)

    p = sub.add_parser("psf", help="fit the pixel PSF model of every exposure from its stars, with diagnostics",
                       description="Star selection, centring, the pixel PSF model (polynomial over the field, "
                                   "constant and linear terms per CCD), astrometric registration; writes "
                                   "EXPOSURE.psfmodel.fits (usable as psf: in the config) and diagnostics.")
    p.add_argument("config", help="the field's YAML config (docs/interface.rst)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="settings that override the config's")
    p.add_argument("--out", default=None, help="output directory (default: psf/ beside the config)")
    p.add_argument("--no-bootstrap", action="store_true", help="skip the bootstrap rms (faster)")
    _add_common(p)
    p.set_defaults(func=_cmd_psf)

    p = sub.add_parser("simulate", help="write a GalSim-simulated field in the input format, plus truth.fits",
                       description="The GREAT-like suite (paper's population, several CCDs, dithered exposures "
                                   "with elliptical Moffat PSFs) or the second suite (Kolmogorov + optics, one "
                                   "exposure, random positions). CONFIG holds preset: (small, cfhtlens, "
                                   "second-small, second) and any simulation key to override.")
    p.add_argument("config", help="YAML of simulation keys")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=None, help="override the config's seed")
    _add_common(p)
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("calibrate", help="fit the noise-bias calibration m(SNR, size) from a measured simulation",
                       description="Sec. 8.4: bins of SNR and size with equal numbers, m and c per bin from the "
                                   "measured minus intrinsic ellipticities, the fit of m = beta / ln(nu) "
                                   "exp(-alpha r nu); writes the YAML (with the (alpha, beta) likelihood grid), the "
                                   "bins as FITS and a plot.")
    p.add_argument("measured", help="shear catalogue of the simulated field (shearfit measure)")
    p.add_argument("truth", help="truth.fits of the simulation")
    p.add_argument("more", nargs="*", metavar="MEASURED TRUTH",
                   help="more fields, as pairs; fields simulated with the same seed (same noise, another shear) "
                        "are paired galaxy by galaxy, so their common noise cancels")
    p.add_argument("--out", required=True, help="calibration YAML to write")
    p.add_argument("--n-snr", type=int, default=20, help="SNR bins (fewer if the sample is small)")
    p.add_argument("--n-size", type=int, default=20, help="size bins per SNR bin")
    p.add_argument("--bootstrap", type=int, default=100, help="bootstrap resamplings per bin")
    p.add_argument("--model", choices=["binned", "paper"], default="binned",
                   help="what measure applies: each SNR-size bin's m (default) or the fitted paper form "
                        "m = beta / ln(nu) exp(-alpha r nu); both are written")
    p.add_argument("--size", choices=["resolution", "scalelength"], default="resolution",
                   help="the table's size axis: the scalelength over the PSF FWHM at the object (default; the "
                        "catalogue's psf_fwhm column), which carries the table to another seeing, or the "
                        "scalelength in arcsec (the paper's)")
    p.add_argument("--seeing-bins", type=int, default=1,
                   help="also a table per range of the PSF FWHM (psf_fwhm; ranges of equal numbers), applied in "
                        "place of the one over all seeing: for simulations that span several seeings")
    p.add_argument("--seed", type=int, default=0)
    _add_common(p)
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("systematics", help="PSF-galaxy cross-correlation against SNR and size, weights, weight bias",
                       description="Sec. 7-8: the weighted <e . e_psf> in bins of SNR and scalelength with errors "
                                   "from 10 random subsamples, per catalogue and combined; weight distributions "
                                   "against magnitude, scalelength and SNR; with --truth, the weight bias <w e_int> "
                                   "against PSF ellipticity in four size x SNR groups. Writes systematics.fits "
                                   "and PNG plots.")
    p.add_argument("catalogs", nargs="+", help="shear catalogue(s) (shearfit measure), e.g. one per field")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--truth", default=None, help="truth.fits of a simulation (for the weight bias)")
    p.add_argument("--n-bins", type=int, default=8, help="bins of SNR, size, magnitude (equal numbers)")
    p.add_argument("--seed", type=int, default=0)
    _add_common(p)
    p.set_defaults(func=_cmd_systematics)

    p = sub.add_parser("xipm", help="calibrated shear two-point functions xi+ and xi- (TreeCorr)",
                       description="xi+ and xi- of the weighted ellipticities (TreeCorr, exact pair binning by "
                                   "default), the calibration term 1+K as the weighted pair average of "
                                   "(1+m_i)(1+m_j), xi/(1+K); with a calibration file, the systematic covariance "
                                   "from its (alpha, beta) likelihood; with --bins, every auto and cross pair of "
                                   "tomographic bins in one file; with --patches, the jackknife covariance.")
    p.add_argument("catalog", help="shear catalogue (shearfit measure)")
    p.add_argument("--out", required=True, help="output FITS file")
    p.add_argument("--min-sep", type=float, default=1.0, help="arcmin")
    p.add_argument("--max-sep", type=float, default=100.0, help="arcmin")
    p.add_argument("--nbins", type=int, default=10, help="angular (logarithmic) bins")
    p.add_argument("--calibration", default=None,
                   help="calibration YAML (shearfit calibrate): m from its alpha, beta and the systematic covariance")
    p.add_argument("--n-sys", type=int, default=100, help="(alpha, beta) draws for the systematic covariance")
    p.add_argument("--select", action="append", default=[], metavar="COLUMN:MIN:MAX",
                   help="keep objects with MIN <= COLUMN < MAX (e.g. a photometric-redshift bin); repeatable; "
                        "applied before --bins")
    p.add_argument("--bins", default=None, metavar="COLUMN:EDGES",
                   help="tomographic bins EDGE_k <= COLUMN < EDGE_k+1 (e.g. z_b:0.2,0.5,0.9,1.3 or zbin:0,1,2): "
                        "xi+- of every pair i <= j, one table HDU XIPM_i_j each")
    p.add_argument("--patches", type=int, default=0, metavar="N",
                   help="jackknife covariance over N TreeCorr patches (k-means on positions, seeded by --seed): "
                        "HDU COV and columns sigma_xip_jk, sigma_xim_jk")
    p.add_argument("--plot", default=None, metavar="FILE.png", help="plot theta*xi+- of every pair of bins")
    p.add_argument("--weight-column", default="weight", metavar="NAME",
                   help="the column of weights (default weight, lensfit's; iso_weight: the same made isotropic, "
                        "which a shear does not change)")
    # 0.0 = shearfit.stats.twopoint.DEFAULT_BIN_SLOP (not imported here: the parser stays free of TreeCorr)
    p.add_argument("--bin-slop", type=float, default=0.0,
                   help="TreeCorr's bin_slop (default 0: exact pair binning; benchmarks/xipm_binning.py)")
    # 0.02 = shearfit.stats.twopoint.DEFAULT_ANGLE_SLOP
    p.add_argument("--angle-slop", type=float, default=0.02,
                   help="TreeCorr's angle_slop in radians (default 0.02: xi- within 0.03 sigma of brute force; "
                        "TreeCorr's own 0.1 moves it by up to 0.2 sigma; 0 is brute force, N^2; "
                        "benchmarks/xipm_binning.py)")
    p.add_argument("--seed", type=int, default=0, help="random seed: calibration draws and patches")
    _add_common(p)
    p.set_defaults(func=_cmd_xipm)

    p = sub.add_parser("noisebias", help="appendix C: the Gaussian model of noise bias, with a Monte Carlo check",
                       description="The expected log-likelihood surface of a Gaussian galaxy with a Gaussian PSF "
                                   "(Fig. C1), the shear bias 1+m and the PSF-galaxy cross-correlation it implies "
                                   "against SNR (Fig. C2), and a Monte Carlo of noisy GalSim images at a few SNR "
                                   "values; writes contours.png, bias.png and noisebias.fits.")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--snr", type=float, nargs="+", default=[5.0, 8.0, 12.0, 20.0, 40.0],
                   help="SNR values of the Monte Carlo")
    p.add_argument("--pairs", type=int, default=2000, help="antithetic noise pairs per orientation and SNR")
    p.add_argument("--seed", type=int, default=0)
    _add_common(p)
    p.set_defaults(func=_cmd_noisebias)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    level = {0: logging.ERROR, 1: logging.WARNING, 2: logging.INFO, 3: logging.DEBUG}[args.verbosity]
    handlers = [logging.StreamHandler(sys.stderr)]
    if args.log_file:
        handlers.append(logging.FileHandler(args.log_file))
    logging.basicConfig(level=level, handlers=handlers, format="%(levelname)s %(name)s: %(message)s", force=True)
    if getattr(args, "n_galaxies", None) is not None and args.n_galaxies < 1:
        print("shearfit: error: --n-galaxies must be at least 1", file=sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except ShearfitError as exc:
        print(f"shearfit: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("shearfit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
