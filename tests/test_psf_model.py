"""Pixel PSF model from stars (sec. 5): recovery of a GalSim PSF varying over the field, registration,
oversampled model, model files, and the ``shearfit psf`` command."""

import galsim
import numpy as np
import pytest

from shearfit.psf.pixelmodel import StarSet, fit_pixel_psf, gaussian_centroid
from shearfit.psf.build import read_psf_model, write_psf_model

PIX = 0.187
N = 25


def _psf_at(ccd, u, v, fwhm0=0.7):
    fwhm = fwhm0 * (1 + 0.08 * u * u + 0.05 * v) + 0.02 * ccd
    e1 = 0.03 + 0.04 * u - 0.02 * v * v + 0.01 * ccd
    e2 = -0.02 + 0.03 * v + 0.02 * u * v
    return galsim.Moffat(beta=3.0, fwhm=fwhm).shear(e1=e1, e2=e2)


def _draw(p, dx, dy, flux=1.0, step=1):
    im = galsim.ImageD(N * step, N * step, scale=PIX / step)
    return galsim.Convolve(p, galsim.Pixel(PIX)).withFlux(flux).drawImage(
        image=im, method="no_pixel", offset=(dx * step, dy * step)).array


def _true_offset(ccd, x, y):
    return np.stack([0.2 - 0.3 * ccd + 0.25 * (x / 2048 - 0.5) - 0.1 * (y / 4096 - 0.5),
                     -0.1 + 0.2 * ccd + 0.15 * (y / 4096 - 0.5)], axis=-1)


def _stars(n_stars, seed=1, snr_min=50, fwhm0=0.7):
    rng = np.random.default_rng(seed)
    ccd = rng.integers(0, 2, n_stars)
    x = rng.uniform(0, 2048, n_stars)
    y = rng.uniform(0, 4096, n_stars)
    u = (x + 2048 * ccd) / 2048 - 1
    v = y / 2048 - 1
    delta = rng.uniform(-0.5, 0.5, (n_stars, 2))
    snr = 10 ** rng.uniform(np.log10(snr_min), 3, n_stars)
    imgs = []
    for i in range(n_stars):
        clean = _draw(_psf_at(ccd[i], u[i], v[i], fwhm0), *delta[i])
        flux = snr[i] * np.sqrt(np.sum(clean ** 2)) / np.sum(clean ** 2)
        imgs.append(flux * clean + rng.normal(0, 1.0, clean.shape))
    # the catalogue (WCS) positions are off by a smooth astrometric error
    nominal = delta - _true_offset(ccd, x, y)
    return StarSet(image=np.array(imgs), ivar=np.ones((n_stars, N, N)), delta=nominal, ccd=ccd, u=u, v=v,
                   x=x, y=y, snr=snr)


@pytest.fixture(scope="module")
def fitted():
    st = _stars(600)
    model, used, info = fit_pixel_psf(st, 2, order=3, ccd_shape=[(4096, 2048)] * 2)
    return st, model, used, info


def test_model_matches_the_true_psf(fitted):
    st, model, _, _ = fitted
    rng = np.random.default_rng(5)
    res, de = [], []
    for _ in range(20):
        c = int(rng.integers(0, 2))
        u = rng.uniform(-1, 0) if c == 0 else rng.uniform(0, 1)
        v = rng.uniform(-1, 1)
        m = model.image(c, u, v)
        t = _draw(_psf_at(c, u, v), 0, 0)
        t /= t.sum()
        res.append(np.sqrt(np.mean((m - t) ** 2)))
        mm = galsim.hsm.FindAdaptiveMom(galsim.Image(m))
        mt = galsim.hsm.FindAdaptiveMom(galsim.Image(t))
        de.append((mm.observed_shape.e1 - mt.observed_shape.e1, mm.observed_shape.e2 - mt.observed_shape.e2))
    # 300 stars per CCD at SNR 50-1000: the paper reports ~3e-4 per pixel; the issue asks < 5e-4
    assert np.mean(res) < 3e-4
    assert np.max(res) < 5e-4
    # ellipticity of the model: noise of 600 stars over 13 terms, about 1.5e-3 rms
    assert np.sqrt(np.mean(np.array(de) ** 2)) < 3e-3


def test_registration_offsets_recovered(fitted):
    st, model, _, _ = fitted
    reg = np.array([model.registration_shift(c, x, y) for c, x, y in zip(st.ccd, st.x, st.y)])
    assert np.max(np.abs(reg - _true_offset(st.ccd, st.x, st.y))) < 0.02


def test_many_positions_at_once_match_one_at_a_time(fitted):
    """images_at and registration_shifts (the pipeline's per-chunk batches) give what image and
    registration_shift give object by object, to rounding."""
    st, model, _, _ = fitted
    for c in (0, 1):
        sel = np.nonzero(st.ccd == c)[0][:5]
        u, v = st.u[sel], st.v[sel]
        many = model.images_at(c, u, v)
        one = np.array([model.image(c, a, b) for a, b in zip(u, v)])
        assert many.shape == one.shape
        np.testing.assert_allclose(many, one, rtol=0, atol=1e-14)
        shifts = model.registration_shifts(c, st.x[sel], st.y[sel])
        np.testing.assert_allclose(shifts, [model.registration_shift(c, x, y) for x, y in zip(st.x[sel], st.y[sel])],
                                   rtol=0, atol=1e-13)


def test_model_is_centred_and_normalised(fitted):
    _, model, _, _ = fitted
    img = model.image(0, -0.5, 0.2)
    assert img.sum() == pytest.approx(1.0)
    cx, cy = gaussian_centroid(img, 1.0, 2.0)
    assert abs(cx) < 0.01 and abs(cy) < 0.01


def test_model_file_round_trip(fitted, tmp_path):
    _, model, _, _ = fitted
    p = tmp_path / "m.psfmodel.fits"
    write_psf_model(model, p)
    back = read_psf_model(p)
    assert np.allclose(back.image(1, 0.3, -0.4), model.image(1, 0.3, -0.4))
    assert back.registration_shift(1, 100.0, 200.0) == pytest.approx(model.registration_shift(1, 100.0, 200.0))


def test_oversampled_model_of_an_undersampled_psf():
    # FWHM 2 pixels: the native model cannot hold the PSF above Nyquist; the 3x model samples it
    st = _stars(300, seed=2, fwhm0=0.374)
    model, _, _ = fit_pixel_psf(st, 2, order=2, oversampling=3, ccd_shape=[(4096, 2048)] * 2)
    m = model.image(1, 0.5, 0.0)
    assert m.shape == (3 * N, 3 * N)
    t = _draw(_psf_at(1, 0.5, 0.0, 0.374), 0, 0, step=3)
    t /= t.sum()
    # against the truth sampled every 1/3 pixel (measured: 0.17 % of the peak; it was 2 % before the
    # alias components had the Moffat-extrapolation prior, which keeps noise out of the unconstrained ones)
    assert np.sqrt(np.mean((m - t) ** 2)) < 0.005 * t.max()
    mm = galsim.hsm.FindAdaptiveMom(galsim.Image(m))
    mt = galsim.hsm.FindAdaptiveMom(galsim.Image(t))
    assert abs(mm.moments_sigma / mt.moments_sigma - 1) < 0.005
    assert abs(mm.observed_shape.e1 - mt.observed_shape.e1) < 0.005
    assert abs(mm.observed_shape.e2 - mt.observed_shape.e2) < 0.005


def test_separable_phase_sums_match_the_full_phase_arrays():
    """The star DFTs and the centring's Newton steps sum the model times exp(-i kappa . delta) as products over
    x and then y (the phase separates): the same numbers as the full (n_s, k, k, n, n) phase array gives, on an
    oversampled model whose aliases make the two axes' orders matter (a swapped axis or alias index fails)."""
    from shearfit.psf import pixelmodel as pm

    st = _stars(60, seed=4, fwhm0=0.5)
    model, used, _ = fit_pixel_psf(st, 2, order=1, oversampling=3, iterations=1, ccd_shape=[(4096, 2048)] * 2)
    rng = np.random.default_rng(5)
    delta = used.delta + rng.uniform(-0.3, 0.3, (len(used), 2))
    P = model.star_spectra(used.ccd, used.u, used.v)
    full = np.sum(P * pm._phases(model.size, 3, delta), axis=(1, 2))
    full = full / full[:, 0, 0].real[:, None, None]
    assert np.abs(model.native_dft(used.ccd, used.u, used.v, delta) - full).max() < 1e-12 * np.abs(full).max()
    # one Newton step of the cross-correlation, from the full array's gradient and Hessian
    D = np.fft.fft2(np.fft.ifftshift(used.image, axes=(-2, -1)))
    E = np.conj(D)[:, None, None] * P * pm._phases(model.size, 3, delta)
    kap = (2 * np.pi / model.size) * pm._fine_freqs(model.size, 3)
    kx, ky = kap[None, None, :, None, :], kap[None, :, None, :, None]
    g = np.stack([np.sum(kx * E, axis=(1, 2, 3, 4)).imag, np.sum(ky * E, axis=(1, 2, 3, 4)).imag], axis=1)
    hxx, hxy, hyy = (-np.sum(a * E, axis=(1, 2, 3, 4)).real for a in (kx * kx, kx * ky, ky * ky))
    det = hxx * hyy - hxy * hxy
    step = -np.stack([hyy * g[:, 0] - hxy * g[:, 1], -hxy * g[:, 0] + hxx * g[:, 1]], axis=1) / det[:, None]
    step *= np.minimum(1.0, 0.5 / np.hypot(step[:, 0], step[:, 1]))[:, None]
    ok = (hxx < 0) & (det > 0)
    assert ok.sum() > len(used) // 2
    one = pm._centre_by_xcorr(model, D, StarSet(*(delta if f == "delta" else getattr(used, f) for f in
                                                  ("image", "ivar", "delta", "ccd", "u", "v", "x", "y", "snr"))),
                              n_newton=1)
    assert np.abs(one[ok] - (delta + step)[ok]).max() < 1e-9


def test_native_prior_keeps_noise_out_of_the_high_frequencies():
    # 100 stars at SNR 20-1000: plain least squares (native_width=0, the paper's fit) puts the stars' noise into
    # every frequency, 2 % of P(0) where the true transform is 1e-4; the prior around the model's Moffat takes it
    # out there and leaves the measured frequencies to the stars (benchmarks/psf_model_test.py --native-width)
    st = _stars(100, seed=3, snr_min=20)
    kf = 2 * np.pi * np.fft.fftfreq(N)
    kk = np.hypot(kf[:, None], kf[None, :])
    out = {}
    for w in (0.0, 1.0):
        model, _, _ = fit_pixel_psf(st, 2, order=3, ccd_shape=[(4096, 2048)] * 2, native_width=w)
        rng = np.random.default_rng(5)
        res, high, low = [], [], []
        for _ in range(10):
            c = int(rng.integers(0, 2))
            u, v = (rng.uniform(-1, 0) if c == 0 else rng.uniform(0, 1)), rng.uniform(-1, 1)
            m = model.image(c, u, v)
            t = _draw(_psf_at(c, u, v), 0, 0)
            t /= t.sum()
            res.append(np.sqrt(np.mean((m - t) ** 2)))
            dP = np.abs(np.fft.fft2(np.fft.ifftshift(m - t)))
            high.append(np.sqrt(np.mean(dP[kk > 2.5] ** 2)))
            low.append(np.sqrt(np.mean(dP[kk < 1.0] ** 2)))
        out[w] = np.mean(res), np.mean(high), np.mean(low)
    assert out[0.0][1] > 1e-2 and out[1.0][1] < 1e-3
    assert out[1.0][0] < 0.6 * out[0.0][0]
    # the well-measured frequencies stay the stars' (not pulled to the circular Moffat)
    assert out[1.0][2] < 1.2 * out[0.0][2]


def test_native_prior_leaves_noise_free_stars_alone():
    # no noise: the stars' residual variance vanishes and with it the prior's weight
    rng = np.random.default_rng(4)
    n = 60
    ccd = rng.integers(0, 2, n)
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    delta = rng.uniform(-0.5, 0.5, (n, 2))
    imgs = np.array([1e4 * _draw(_psf_at(0, 0.0, 0.0), *delta[i]) for i in range(n)])
    st = StarSet(image=imgs, ivar=np.ones((n, N, N)), delta=delta, ccd=ccd, u=u, v=v, x=np.zeros(n),
                 y=np.zeros(n), snr=np.full(n, 1e4))
    a, _, _ = fit_pixel_psf(st, 2, order=1, native_width=0.0)
    b, _, _ = fit_pixel_psf(st, 2, order=1, native_width=1.0)
    ia, ib = a.image(0, 0.1, 0.2), b.image(0, 0.1, 0.2)
    assert np.max(np.abs(ia - ib)) < 1e-6 * ia.max()


def test_too_few_stars_is_an_error():
    from shearfit.errors import ShearfitValueError

    st = _stars(6)
    with pytest.raises(ShearfitValueError, match="stars cannot constrain"):
        fit_pixel_psf(st, 2, order=3)
