"""The compiled inner loops against the numpy ones, end to end: the same galaxies measured on both paths.

The numpy path evaluates every Fourier mode (it has no mode binning: ``mode_bins_per_octave`` is the compiled
path's only, see ``docs/configuration``); with ``mode_bins_per_octave = 0`` the two paths do the same
arithmetic and agree to rounding (the numpy path indexes the profile table in float32: 1e-6 relative on the
sums), and with the default binning they differ by the binning's stated approximation (|delta e| < 1e-4).
"""

import numpy as np
import pytest

import shearfit
from shearfit.engine import kernel, likelihood, model, sampling
from shearfit.simulate import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr

PIX = 0.187

pytestmark = pytest.mark.skipif(kernel.KERNEL is None, reason="compiled kernel not built")


def _galaxy(seed):
    """Three exposures of a noisy galaxy with distinct Jacobians and PSFs (GalSim renders them)."""
    rng = np.random.default_rng(seed)
    r, B = rng.uniform(0.2, 0.6), rng.uniform(0.0, 0.3)
    e = rng.uniform(-0.4, 0.4, 2)
    gal = galaxy_profile(r, B, e[0], e[1], flux=1000.0)
    obs = []
    for i in range(3):
        t = np.radians(rng.uniform(-5, 5))
        J = PIX * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) @ np.array([[1.01, 0.0], [0.0, 0.99]])
        psf = moffat_psf(0.6 + 0.05 * i, 3.0, 0.04 * (-1) ** i, 0.03)
        off = rng.uniform(-0.5, 0.5, 2)
        im = draw_stamp(gal, psf, J, off)
        sig = noise_for_snr([im], 25.0)
        obs.append(shearfit.Observation(image=im + rng.normal(0, sig, im.shape), weight=np.full(im.shape, sig ** -2),
                                        psf=draw_psf_image(psf, J, size=48), jacobian=J, offset=tuple(off)))
    return obs


def _numpy_path(monkeypatch):
    for mod, name in ((likelihood, "USE_KERNEL"), (likelihood, "USE_KERNEL_MARGINAL"), (sampling, "USE_KERNEL"),
                      (model, "USE_KERNEL")):
        monkeypatch.setattr(mod, name, False)


@pytest.mark.parametrize("bins_per_octave, tol", [(0, 2e-6), (16, 1e-4)])
def test_compiled_and_numpy_paths_measure_the_same(monkeypatch, bins_per_octave, tol):
    cfg = {"mode_bins_per_octave": bins_per_octave}
    objects = [_galaxy(seed) for seed in (3, 4)]
    compiled = [shearfit.measure_object(o, mag=22.5, config=cfg) for o in objects]
    with monkeypatch.context() as m:
        _numpy_path(m)
        numpy = [shearfit.measure_object(o, mag=22.5, config=cfg) for o in objects]
    for a, b in zip(compiled, numpy):
        assert a.fitclass == b.fitclass == 0
        assert abs(a.e1 - b.e1) < tol and abs(a.e2 - b.e2) < tol, (a.e1 - b.e1, a.e2 - b.e2)
        assert a.scalelength == pytest.approx(b.scalelength, rel=1e-3)


def test_kernel_info_names_the_path_and_instruction_set():
    info = kernel.kernel_info()
    assert info["path"] in ("compiled", "numpy")
    assert "baseline" in info["built"]
    if kernel.USE_KERNEL:
        assert info["isa"] in [name for name, _, _ in kernel.LEVELS] + ["x86-64-v3 (AVX2)", "x86-64-v4 (AVX-512)"]
        assert info["isa"].split()[0] in info["cpu_levels"] and info["compiler"]


_SCRIPT = """
import json, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_kernel import _galaxy
import shearfit
from shearfit.engine.kernel import kernel_info
res = [shearfit.measure_object(_galaxy(seed), mag=22.5) for seed in (3, 4)]
print(json.dumps({{"isa": kernel_info()["isa"], "e": [[r.e1, r.e2] for r in res]}}))
"""


def test_every_instruction_set_level_measures_the_same(tmp_path):
    """SHEARFIT_ISA forces each built level the CPU runs (and the numpy loops); the estimates agree to the
    binning's approximation (the levels differ in rounding: FMA contraction, vector widths)."""
    import json
    import os
    import pathlib
    import subprocess
    import sys

    info = kernel.kernel_info()
    levels = [name for name in info["built"] if name in info["cpu_levels"]] + ["numpy"]
    out = {}
    for level in levels:
        env = dict(os.environ, SHEARFIT_ISA=level)
        run = subprocess.run([sys.executable, "-c", _SCRIPT.format(tests=str(pathlib.Path(__file__).parent))],
                             env=env, capture_output=True, text=True, check=True, cwd=tmp_path)
        out[level] = json.loads(run.stdout.strip().splitlines()[-1])
        want = "numpy" if level == "numpy" else level
        assert out[level]["isa"].split()[0] == want
    ref = np.array(out[levels[0]]["e"])
    for level in levels[1:]:
        # the numpy loops evaluate every mode: they differ from the binned compiled loops by the binning's 1e-4
        assert np.max(np.abs(np.array(out[level]["e"]) - ref)) < 1e-4, level


def test_missing_compiled_kernel_warns_once_and_runs_numpy(tmp_path):
    """Without any compiled module (no C compiler at install time) import shearfit warns once, naming the
    missing module, and the numpy loops run (kernel_info says so); the catalogue header would say 'numpy'."""
    import os
    import subprocess
    import sys

    code = """
import sys, warnings
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.startswith("shearfit.engine._kernels"):
            raise ImportError("blocked for the test: " + name)
sys.meta_path.insert(0, Block())
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    import shearfit
    from shearfit.engine.kernel import kernel_info
    import shearfit.engine.likelihood, shearfit.engine.sampling
msgs = [str(x.message) for x in w if "compiled kernel" in str(x.message)]
print(len(msgs), kernel_info()["path"], kernel_info()["isa"])
print(msgs[0] if msgs else "")
"""
    env = {k: v for k, v in os.environ.items() if k not in ("SHEARFIT_ISA", "SHEARFIT_NO_KERNEL")}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                         cwd=tmp_path)
    first, message = run.stdout.strip().splitlines()[:2]
    assert first == "1 numpy numpy"
    assert "shearfit.engine._kernels" in message and "numpy loops run instead" in message


@pytest.mark.parametrize("rs, beta", [(0.3, 1.2), (1.7, 3.1), (4.5, 2.2), (40.0, 15.0)])
@pytest.mark.parametrize("s", [1, 3, 5])
def test_alias_tables_compiled_and_numpy_agree(monkeypatch, rs, beta, s):
    """The App. A Moffat's table (Hermite segments) and alias sums in C are the numpy lines' numbers to
    rounding; a wrong alias order, a segment off by one point or a missing kept alias fails it."""
    tabs = {}
    for use in (True, False):
        monkeypatch.setattr(model, "USE_KERNEL", use)
        model._moffat_aliases.cache_clear()
        k = model._alias_geometry(48, 40, s)[0]
        tabs[use] = (model._moffat_table(k, rs, beta), model._moffat_aliases(rs, beta, 48, 40, s))
    model._moffat_aliases.cache_clear()
    (t1, a1), (t0, a0) = tabs[True], tabs[False]
    assert np.abs(t1 - t0).max() < 1e-14
    # A, ok, G of the kept aliases and each mode's largest |G|^2 (the compiled tables leave |G| to the selection,
    # which squares G: None there)
    assert a1[3] is None
    for x, y in zip([a1[0], a1[1], a1[2], np.abs(a1[2]), a1[7]], [a0[0], a0[1], a0[2], a0[3], a0[7]]):
        assert x.shape == y.shape
        assert np.abs(np.asarray(x, float) - np.asarray(y, float)).max() < 1e-14


@pytest.mark.parametrize("shape", [(48, 48), (48, 40), (47, 50), (33, 33)])
@pytest.mark.parametrize("s", [1, 3, 5])
def test_alias_sums_from_half_the_rows_are_the_same_numbers(shape, s):
    """The App. A alias tables made from half the rows (alias_sums_mirror: row ny - r read from row r's mirrored
    aliases) are alias_sums' to the bit, even and odd grids alike; a row read from the wrong mirror, or an alias
    order not mirrored, fails it (the sums' order is the same alias order)."""
    if model.KERNEL is None or not model.USE_KERNEL:
        pytest.skip("the compiled kernel is not in use")
    ny, nx = shape
    assert model._alias_mirrored(ny, nx, s)
    ktab, i0, w0, w1 = model._alias_geometry(ny, nx, s)[:4]
    kept = model._kept_aliases(ny, nx, s)
    for rs, beta in [(0.7, 1.4), (2.4, 2.6), (5.0, 4.3)]:
        mtab = model._moffat_table(ktab, rs, beta)
        out = []
        for mirror in (False, True):
            A, Gs, M = np.empty(i0.shape[2:]), np.empty(kept.size * ny * (nx // 2 + 1)), np.empty(i0.shape[2:])
            if mirror:
                model.KERNEL.alias_sums_mirror(mtab, i0, w0, w1, kept, A, Gs, M, ny, nx // 2 + 1, i0.shape[0])
            else:
                model.KERNEL.alias_sums(mtab, i0, w0, w1, kept, A, Gs, M)
            out.append((A, Gs, M))
        for x, y in zip(*out):
            assert np.array_equal(x, y)


@pytest.mark.parametrize("s", [1, 3, 5])
@pytest.mark.parametrize("shape, offset", [((48, 48), None), ((48, 48), (0.31, -0.27)), ((47, 50), (-0.4, 0.12))])
def test_fine_modes_compiled_and_numpy_agree(monkeypatch, s, shape, offset):
    """The native PSF's modes with the App. A alias correction (fine_modes_select in C): the same modes in the
    same order, wavevectors and sampled modes exactly, transfers to rounding, for a GalSim-drawn elliptical
    Moffat whose own App. A Moffat is another; a mode selected by the wrong alias's |G|, a phase on the wrong
    axis or a row skipped fails it."""
    ny, nx = shape
    psf = draw_psf_image(moffat_psf(0.7, 3.5, 0.05, -0.03), PIX * np.eye(2), size=25)
    out = {}
    for use in (True, False):
        monkeypatch.setattr(model, "USE_KERNEL", use)
        model._moffat_aliases.cache_clear()
        out[use] = model._fine_modes_moffat(psf, ny, nx, s, moffat=(2.1, 3.4), tolerance=1e-6, offset=offset)
    model._moffat_aliases.cache_clear()
    (ky1, kx1, T1, c1), (ky0, kx0, T0, c0) = out[True], out[False]
    assert c1.size == c0.size and c1.size > ny * (nx // 2 + 1) // 2
    assert np.array_equal(ky1, ky0) and np.array_equal(kx1, kx0) and np.array_equal(c1, c0)
    assert np.abs(T1 - T0).max() < 1e-14 * np.abs(T0).max()


def test_compiled_complex_bincount_is_the_numpy_lines():
    """model.complex_bincount compiled (one pass, KERNEL.complex_bincount) gives its numpy lines' sums to the bit:
    repeated and unordered indices, empty bins, bins of -0.0 values alone (+0.0: the sums start from 0.0), and an
    index beyond n, which the compiled call refuses and the numpy lines widen the result for."""
    if model.KERNEL is None or not model.USE_KERNEL:
        pytest.skip("the compiled kernel is not in use")
    rng = np.random.default_rng(5)
    for n, m in [(1, 1), (50, 400), (5033, 5038)]:
        idx = rng.integers(0, max(n - 1, 1), m)
        vals = rng.normal(size=m) * 10.0 ** rng.uniform(-8, 8, m) + 1j * rng.normal(size=m)
        vals[: m // 7] = -0.0 - 0.0j
        got = model.complex_bincount(idx, vals, n)
        want = model.complex_bincount(idx, vals, n, use_kernel=False)
        assert got.shape == want.shape == (n,)
        assert np.array_equal(got.view(float), want.view(float))
        assert not np.signbit(got.view(float)[got.view(float) == 0]).any()
    idx = np.array([0, 3, 9], np.int64)
    vals = np.array([1.0, 2.0, 3.0], complex)
    got = model.complex_bincount(idx, vals, 5)
    assert np.array_equal(got, model.complex_bincount(idx, vals, 5, use_kernel=False)) and got.size == 10


def test_compiled_banded_product_is_the_dense_one():
    """metacal.dilated_image over its matrices' bands (KERNEL.banded_rows, for images four times as wide as the band)
    gives the dense matrix products' pixels to rounding: square and oblong PSF images oversampled 3 times, dilated
    and shrunk; each band holds every non-zero value of its matrix. A band reaching past the matrix is refused."""
    from shearfit.calib import metacal

    if model.KERNEL is None or not model.USE_KERNEL:
        pytest.skip("the compiled kernel is not in use")
    rng = np.random.default_rng(2)
    for shape, d in (((144, 144), 1.02), ((150, 126), 1.02), ((144, 144), 0.97)):
        img = rng.normal(size=shape)
        want = metacal._dilation_matrix(shape[0], d) @ img @ metacal._dilation_matrix(shape[1], d).T
        got = metacal.dilated_image(img, d)
        assert got.shape == want.shape and got.flags.c_contiguous
        assert np.abs(got - want).max() < 1e-14 * np.abs(want).max(), (shape, d)
        for n in shape:
            values, start = metacal._dilation_band(n, d)
            dense = np.zeros((n, n))
            dense[np.arange(n)[:, None], start[:, None] + np.arange(values.shape[1])] = values
            assert np.array_equal(dense, metacal._dilation_matrix(n, d)) and 4 * values.shape[1] <= n
    values, start = metacal._dilation_band(144, 1.02)
    with pytest.raises(ValueError, match="banded_rows"):
        model.KERNEL.banded_rows(values, start + 1, np.ones((144, 3)), np.empty((144, 3)))
