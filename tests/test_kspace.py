"""Metacal's own k-space operations (shearfit.calib.kspace) against GalSim and the discrete transform."""

import galsim
import numpy as np
import pytest

from shearfit.calib import kspace, metacal
from shearfit.engine.kernel import USE_KERNEL

from test_metacal import PIX, _obs


def _dtft(im, kx, ky, n):
    """The discrete-time transform of ``im`` about its pixel (ny // 2, nx // 2) at 2 pi (kx, ky) / n."""
    ny, nx = im.shape
    y, x = np.mgrid[:ny, :nx]
    return np.array([np.sum(im * np.exp(-2j * np.pi * (a * (x - nx // 2) + b * (y - ny // 2)) / n))
                     for a, b in zip(kx, ky)])


def test_quintic_kernel_is_galsims():
    x = np.linspace(-3.5, 3.5, 20001)
    assert np.abs(kspace.quintic(x) - galsim.Quintic().xval(x)).max() < 1e-14


@pytest.mark.parametrize("shape", [(48, 48), (25, 25), (41, 36)])
def test_table_points_are_the_discrete_transform_and_between_them_close(shape):
    """At the padded grid's points the interpolated transform is the images' discrete-time transform (to
    rounding), for even, odd and oblong images; between them within 5e-4 of the peak (the quintic on a grid
    padded four times); every image of the table with one set of weights."""
    rng = np.random.default_rng(3)
    ims = [rng.normal(size=shape), rng.normal(size=shape) + 1.0]
    n = kspace.padded_size(shape)
    table = kspace.padded_transforms(ims, n)
    kx = np.array([0.0, 3.0, -7.0, 50.0, -n / 2])
    ky = np.array([0.0, -2.0, 11.0, -90.0, n / 2 - 1])
    at = kspace.kvalues(table, kx, ky)
    tx, ty = rng.uniform(-n / 2, n / 2, (2, 200))
    between = kspace.kvalues(table, tx, ty)
    for t, im in enumerate(ims):
        peak = np.abs(im).sum()
        assert np.abs(at[:, t] - _dtft(im, kx, ky, n)).max() < 1e-12 * peak
        assert np.abs(between[:, t] - _dtft(im, tx, ty, n)).max() < 5e-4 * peak


@pytest.mark.skipif(not USE_KERNEL, reason="the compiled loops are not built")
def test_compiled_interpolation_is_the_numpy_reference():
    rng = np.random.default_rng(4)
    ims = [rng.normal(size=(48, 48)), rng.normal(size=(48, 48)), rng.normal(size=(25, 25))]
    n = kspace.padded_size((48, 48))
    table = kspace.padded_transforms(ims, n)
    tx, ty = rng.uniform(-n / 2 - 4, n / 2 + 4, (2, 3000))   # across the periodic and Hermitian edges
    for sub in (table, table[2:3]):
        ref = kspace.kvalues_numpy(sub, tx, ty)
        assert np.abs(kspace.kvalues(sub, tx, ty) - ref).max() < 1e-12 * np.abs(ref).max()


JACOBIANS = [PIX * np.array([[-1.0, 0.0], [0.0, 1.0]]), PIX * np.array([[0.3, -0.95], [0.94, 0.31]])]


@pytest.mark.parametrize("J", JACOBIANS)
def test_band_edge_is_where_galsims_psf_transform_falls_below_the_threshold(J):
    """The deconvolution's band: GalSim's transform of the same interpolated PSF exceeds 1e-3 of its flux
    somewhere within 5 % of the band's edge, and nowhere 3 % beyond it, unless the band is the pixels' Nyquist
    disc (a PSF sharp enough to be aliased: 0.6" here), which it then equals."""
    ang = np.linspace(0, 2 * np.pi, 721)[:-1]
    for fwhm in (0.6, 0.75, 0.9):
        psf = galsim.Moffat(fwhm=fwhm, beta=3.0).shear(g1=0.04, g2=0.03)
        img = psf.drawImage(nx=25, ny=25, wcs=metacal._wcs(J), method="no_pixel").array
        ii = metacal._interpolated(img, metacal._wcs(J))
        n = kspace.padded_size(img.shape, (48, 48))
        band = kspace.band_maxk(kspace.padded_transforms([img], n)[0], metacal._LANCZOS.kval, J)
        nyquist = np.pi / np.linalg.svd(J, compute_uv=False)[0]

        def amp(radius):
            return np.array([abs(ii.kValue(galsim.PositionD(radius * np.cos(a), radius * np.sin(a))))
                             for a in ang]) / ii.flux

        if band < nyquist:
            assert amp(1.03 * band).max() < 1e-3, fwhm
            assert max(amp(f * band).max() for f in (0.95, 0.97, 0.99)) > 1e-3, fwhm
        else:
            assert fwhm == 0.6 and abs(band / nyquist - 1) < 1e-12
            assert amp(0.99 * band).max() > 1e-3


@pytest.mark.parametrize("J", JACOBIANS)
@pytest.mark.parametrize("snr", [None, 40])
def test_own_versions_are_galsims_with_its_band(J, snr, monkeypatch):
    """Given GalSim's band (its maxk of the PSF), the versions made by shearfit's own k-space operations are
    those of GalSim's objects to 1e-6 of the peak without noise and 2e-5 with it (the two pad the PSF's
    transform differently), weights to 1e-5, on a reflected and on a rotated, sheared pixel grid."""
    obs = _obs(0.3, (0.2, -0.1), snr=snr, n_exp=1, seed=4, J=J)[0]
    maxk = metacal._interpolated(obs.psf, metacal._wcs(J), calculate_maxk=True).maxk
    monkeypatch.setattr(kspace, "band_maxk", lambda *a, **k: maxk)
    out = {}
    for own in (True, False):
        monkeypatch.setattr(metacal, "OWN_KSPACE", own)
        out[own] = metacal.metacal_observations(obs, rng=np.random.default_rng(5))
    good = out[False]["noshear"].weight > 0
    peak = np.abs(out[False]["noshear"].image[good]).max()
    tol = 1e-6 if snr is None else 2e-5
    for name, ref in out[False].items():
        assert np.abs(out[True][name].image - ref.image)[good].max() < tol * peak, name
        assert np.allclose(out[True][name].weight, ref.weight, rtol=1e-5, atol=0)
        assert np.array_equal(out[True][name].psf, ref.psf)


def test_oversampled_psfs_and_other_interpolants_take_galsims_path(monkeypatch):
    """The own operations serve native PSFs with the quintic k-interpolant; an oversampled PSF, another
    interpolant or GalSim's own FFT grid goes through GalSim's objects."""
    calls = []
    real = metacal.own_kspace_images
    monkeypatch.setattr(metacal, "own_kspace_images", lambda *a, **k: calls.append(1) or real(*a, **k))
    obs = _obs(0.3, (0.2, -0.1), n_exp=1, seed=4)[0]
    metacal.metacal_observations(obs, rng=np.random.default_rng(1))
    assert len(calls) == 1
    for name, value in (("K_INTERPOLANT", "cubic"), ("WRAP_STAMPS", 0)):
        with monkeypatch.context() as m:
            m.setattr(metacal, name, value)
            metacal.metacal_observations(obs, rng=np.random.default_rng(1))
    assert len(calls) == 1


def _fold_brute(arr, n):
    """One band folded point by point from the full plane it stands for: F(i, j) stored for i >= 0, F(-i, -j) =
    conj F(i, j); every point lands at (i mod n, j mod n), kept where that column is stored (<= n // 2)."""
    r = arr.shape[1] - 1
    half = n // 2
    out = np.zeros((n, half + 1), complex)
    for j in range(-r, r + 1):
        for i in range(-r, r + 1):
            v = arr[j + r, i] if i >= 0 else np.conj(arr[-j + r, -i])
            if i % n <= half:
                out[j % n, i % n] += v
    return out


@pytest.mark.parametrize("n", [64, 48, 45, 8, 7])
def test_band_fold_is_galsims_wrap_and_the_full_planes_fold(n):
    """The versions' bands are folded onto the FFT grid as the full plane they stand for folds (periodic in n,
    the stored half's mirrors conjugated), which for even n is GalSim's ``Image.wrap(hermitian='x')``: for
    bands narrower than the grid, as wide as it, and several times wider (GalSim's own k grid)."""
    rng = np.random.default_rng(n)
    half = n // 2
    for r in sorted({max(half - 2, 0), half, half + 1, n - 1, n, n + 3, 2 * n + 1}):
        arr = rng.normal(size=(2, 2 * r + 1, r + 1)) + 1j * rng.normal(size=(2, 2 * r + 1, r + 1))
        mine = metacal.fold_band(arr, n)
        for b in range(2):
            assert np.abs(mine[b] - _fold_brute(arr[b], n)).max() < 1e-12
            if n % 2 == 0 and r >= half:
                full = galsim.ImageCD(galsim.BoundsI(0, r, -r, r), scale=1.0)
                full.array[:, :] = arr[b]
                ref = full.wrap(galsim.BoundsI(0, half, -half, half - 1), hermitian="x").array
                assert np.abs(mine[b][np.arange(-half, half) % n] - ref).max() < 1e-12
