"""benchmarks/field_test.py --table: a field's catalogues as a ring-test table, several seeds read as one."""

import re

import numpy as np
from astropy.table import Table

from scripts import load_script

ring_split = load_script("benchmarks/ring_split.py")   # puts benchmarks/ on the path, for field_test's imports
field_test = load_script("benchmarks/field_test.py")

G = (0.03, -0.02)


class _Args:
    shear = G


def _field(m, n_rings, seed):
    """``field_test.py``'s galaxies (4 orientations a ring) and the catalogues of its four fields (+g and -g, each
    with its antithetic twin) whose estimates respond to the shear by 1 + m exactly, the noise the same at +g and
    -g and negated in the twin."""
    rng = np.random.default_rng(seed)
    gals = []
    for k in range(n_rings):
        e0 = rng.uniform(0.05, 0.6) * np.exp(2j * np.pi * rng.uniform())
        r = rng.uniform(0.1, 0.125)
        for j in range(4):
            ej = e0 * np.exp(1j * np.pi * j / 2)
            gals.append(dict(ring=k, r=r, B=0.0, e1=ej.real, e2=ej.imag))
    noise = rng.normal(0, 0.05, (len(gals), 2)) @ np.array([1, 1j])
    tables = {}
    for sign in (1, -1):
        for twin in (1, -1):
            e = np.array([g["e1"] + 1j * g["e2"] for g in gals]) + (1 + m) * sign * complex(*G) + twin * noise
            n = len(gals)
            tables[(sign, twin)] = Table({"e1": e.real, "e2": e.imag, "e_var": np.full(n, 0.01),
                                          "weight": rng.uniform(5, 10, n), "iso_weight": np.full(n, 7.0),
                                          "fitclass": np.zeros(n, int), "m": np.zeros(n),
                                          "flux_snr": rng.uniform(100, 200, n), "round_scalelength": np.full(n, 0.11)})
    return tables, gals


def test_two_seeds_tables_read_as_one_by_ring_split(tmp_path, capsys):
    paths = []
    for seed, n in ((1, 30), (2, 20)):
        tables, gals = _field(0.004, n, seed)
        t = field_test.ring_table(tables, gals, _Args())
        assert len(t) == 8 * n * 2
        # each ring's eight objects at each shear: orientations 0-3 and the twin's 4-7
        assert set(np.asarray(t["rotation"])) == set(range(8))
        assert np.all(np.bincount(np.asarray(t["galaxy"]), minlength=n) == 16)
        assert np.allclose(np.asarray(t["g1"]) * np.asarray(t["sign"]), G[0])
        paths.append(tmp_path / f"t{seed}.fits")
        t.write(paths[-1])
    ring_split.main([str(p) for p in paths], r_bins=(0.1, 0.125), unweighted=True)
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("all"))
    assert "rings=  50" in line
    m = [float(x) for x in re.findall(r"m[12]=([+-][0-9.]+)", line)]
    assert np.allclose(m, 0.004, atol=1e-4)


def test_keep_stars_counts_the_objects_classified_as_stars(tmp_path, capsys):
    """An object classified as a star at +g and not at -g leaves its ring's shapes uncancelled; --keep-stars
    counts it again, and m is the estimates' own."""
    tables, gals = _field(-0.003, 30, 3)
    tables[(1, 1)]["fitclass"][[5, 17]] = 1
    path = tmp_path / "t.fits"
    field_test.ring_table(tables, gals, _Args()).write(path)
    for keep, close in ((False, False), (True, True)):
        ring_split.main([str(path)], r_bins=(0.1, 0.125), unweighted=True, keep_stars=keep)
        line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("all"))
        m = [float(x) for x in re.findall(r"m[12]=([+-][0-9.]+)", line)]
        assert np.allclose(m, -0.003, atol=1e-4) == close


def test_each_wcs_variant_reports_the_leakage_along_its_own_sky_psf(capsys):
    """Rotated and distorted exposures carry the same pixel PSFs to the sky differently: each variant's report
    takes its own exposures' sky-frame PSF, and c = alpha e_psf there gives alpha back."""
    class Args:
        shear, n_galaxies, n_bootstrap, n_exposures, n_ccd = G, 30, 50, 2, 1
        antithetic, noise_free, noise_sigma, metacal = True, True, None, False
        snr_min, snr_max, min_size, size_split = 100.0, 200.0, 0.1, None
        psf_sky = {"plain": np.array([[0.01, 0.02, 0.7], [0.03, -0.01, 0.6]]),
                   "distorted": np.array([[0.05, 0.00, 0.7], [0.04, -0.02, 0.6]])}
    alpha = 0.02
    for mode, sky in Args.psf_sky.items():
        w = sky[:, 2] ** -4.0
        e_psf = w @ sky[:, :2] / w.sum()
        tables, gals = _field(0.0, Args.n_galaxies, 4)
        for t in tables.values():
            t["weight"] = 7.0   # equal weights: each ring's intrinsic shapes cancel, and c is alpha e_psf alone
            t["e1"] += alpha * e_psf[0]
            t["e2"] += alpha * e_psf[1]
        field_test.report(tables, gals, Args(), mode, mode)
        out = capsys.readouterr().out
        found = re.search(r"alpha = ([+-][0-9.]+) \+/- ([0-9.]+)", out)
        assert found and abs(float(found.group(1)) - alpha) < 1e-4, out
        assert f"({e_psf[0]:+.4f}, {e_psf[1]:+.4f})" in out


def test_report_gives_m_on_whole_rings_where_an_object_was_flagged(capsys):
    """One flagged object (fitclass -3) breaks its ring in the catalogue's m; the report's whole-rings line leaves
    that ring out, gives back the m the estimates were made with, and says where the flagged object was."""
    class Args:
        shear, n_galaxies, n_bootstrap, n_exposures, n_ccd = G, 30, 50, 2, 1
        antithetic, noise_free, noise_sigma, metacal = True, False, None, False
        snr_min, snr_max, min_size, size_split = 100.0, 200.0, 0.1, None
    tables, gals = _field(0.004, Args.n_galaxies, 6)
    for t in tables.values():
        t["weight"] = 7.0
    tables[(-1, 1)]["fitclass"][9] = -3   # ring 2, at -g
    field_test.report(tables, gals, Args(), "given", "plain")
    out = capsys.readouterr().out
    whole = re.search(r"whole rings only \(1 rings .* 0 at \+g, 1 at -g\): m1 = ([+-][0-9.]+) .* m2 = ([+-][0-9.]+)",
                      out)
    assert whole, out
    assert np.allclose([float(whole.group(1)), float(whole.group(2))], 0.004, atol=1e-4)
    broken = [float(x) for x in re.findall(r"^  m[12] = ([+-][0-9.]+)", out, re.M)]
    assert np.max(np.abs(np.subtract(broken, 0.004))) > 1e-3


def _metacal_field(m, n_rings, seed, r=0.8, delta=0.01):
    """``_field``'s catalogues as a metacal run's: the noshear estimates respond to the shear by r (1 + m), each
    sheared version's by r to metacal's step, R = r times the identity, no selection."""
    tables, gals = _field(0.0, n_rings, seed)
    g = np.array(G)
    for (sign, _), t in tables.items():
        for c in (0, 1):
            t[f"e{c + 1}"] = t[f"e{c + 1}"] + (r * (1 + m) - 1) * sign * g[c]
        for v, (d1, d2) in {"1p": (delta, 0.0), "1m": (-delta, 0.0), "2p": (0.0, delta), "2m": (0.0, -delta)}.items():
            t[f"e1_{v}"], t[f"e2_{v}"] = t["e1"] + r * d1, t["e2"] + r * d2
            t[f"weight_{v}"], t[f"fitclass_{v}"] = t["weight"], t["fitclass"]
        t["R11"], t["R22"] = np.full(len(t), r), np.full(len(t), r)
        t["R12"], t["R21"] = np.zeros(len(t)), np.zeros(len(t))
        t["snr"], t["scalelength"] = t["flux_snr"], np.full(len(t), 0.11)
    return tables, gals


def test_metacal_field_tables_give_metacal_m_and_paired_differences(tmp_path, capsys):
    """A metacal field's table carries the versions and R (ring_test.py's metacal columns): ring_test.py
    --from-tables ... --metacal reads it for metacal's m (unit weights: each ring's twins cancel exactly), and
    --paired-with another run of the same fields gives the two runs' difference of m."""
    ring_test = load_script("benchmarks/ring_test.py")
    paths = {}
    for name, m in (("a", 0.004), ("b", 0.001)):
        tables, gals = _metacal_field(m, 30, 7)
        t = field_test.ring_table(tables, gals, _Args())
        assert all(key in t.colnames for key in ring_test.METACAL_FIELDS)
        assert t["fitclass_1p"].dtype.kind == "i"
        paths[name] = str(tmp_path / f"{name}.fits")
        t.write(paths[name])
    assert ring_test.main(["--from-tables", paths["a"], "--metacal", "--unweighted"]) in (0, None)
    out = capsys.readouterr().out
    metacal = out[out.index("metacal shear bias"):]
    m = [float(x) for x in re.findall(r"m[12] = +([+-][0-9.]+)", metacal)[:2]]
    assert np.allclose(m, 0.004, atol=1e-5), metacal
    assert ring_test.main(["--from-tables", paths["a"], "--metacal", "--paired-with", paths["b"]]) in (0, None)
    out = capsys.readouterr().out
    paired = out[out.index("these tables less --paired-with's"):]
    d = [float(x) for x in re.findall(r"delta m[12] = +([+-][0-9.]+)", paired)[:2]]
    assert np.allclose(d, 0.003, atol=1e-5), paired
