"""benchmarks/ring_split.py --paired-with: two runs of the same galaxies compared object by object."""

import re

import numpy as np
from astropy.table import Table

from scripts import load_script

ring_split = load_script("benchmarks/ring_split.py")

G = (0.03, -0.02)


def _run(m, n_gal=40, twins=True, drop=(), seed=5):
    """A ring-test-like table whose estimates respond to the shear by 1 + m exactly: e = e_int + (1 + m) g sign
    + n, with n the same at +g and -g (a twin has -n)."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n_gal):
        if k in drop:
            continue
        e0 = rng.uniform(0.05, 0.6) * np.exp(2j * np.pi * rng.uniform())
        for j in range(8 if twins else 4):
            ej = e0 * np.exp(2j * np.pi * (j % 4) / 4)
            noise = complex(*np.random.default_rng([seed, k, j % 4]).normal(0, 0.05, 2)) * (-1 if j >= 4 else 1)
            for sign in (1, -1):
                e = ej + (1 + m) * sign * complex(*G) + noise
                rows.append((k, sign, j, G[0] * sign, G[1] * sign, ej.real, ej.imag, 0.11, e.real, e.imag, 0.01,
                             1.0, 0, 100.0))
    names = ("galaxy", "sign", "rotation", "g1", "g2", "e1_int", "e2_int", "true_scalelength", "e1", "e2", "e_var",
             "weight", "fitclass", "flux_snr")
    return Table(rows=rows, names=names)


def _pairs(out):
    """m1, m2 of the "all" lines: the first run, the paired run, the first less the paired."""
    lines = [ln for ln in out.splitlines() if ln.startswith("all")]
    return [tuple(float(x) for x in re.findall(r"m[12]=([+-][0-9.]+)", ln)) for ln in lines], lines


def test_paired_with_is_the_difference_object_by_object(tmp_path, capsys):
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    _run(0.004).write(a)
    # the other run: noise-free-like, without twins, and a stopped run's table lacking galaxy 3 (as written: the
    # galaxies keep their numbers)
    _run(-0.002, twins=False, drop=(3,)).write(b)
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True, paired_with=[str(b)])
    (first, other, diff), lines = _pairs(capsys.readouterr().out)
    assert "rings=  39" in lines[2]
    assert np.allclose(first, 0.004, atol=1e-4)
    assert np.allclose(other, -0.002, atol=1e-4)
    assert np.allclose(diff, 0.006, atol=1e-4)
