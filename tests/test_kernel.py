"""The compiled inner loops against the numpy ones, end to end: the same galaxies measured on both paths.

The numpy path evaluates every Fourier mode (it has no mode binning: ``mode_bins_per_octave`` is the compiled
path's only, see ``docs/configuration``); with ``mode_bins_per_octave = 0`` the two paths do the same
arithmetic and agree to rounding (the numpy path indexes the profile table in float32: 1e-6 relative on the
sums), and with the default binning they differ by the binning's stated approximation (|delta e| < 1e-4).
"""

import numpy as np
import pytest

import shearfit
from shearfit.engine import kernel, likelihood, sampling
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
    for mod, name in ((likelihood, "USE_KERNEL"), (likelihood, "USE_KERNEL_MARGINAL"), (sampling, "USE_KERNEL")):
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
    if kernel.USE_KERNEL:
        assert info["isa"].startswith(("x86-64", "portable"))
        assert info["multiversion"] and info["compiler"]
