"""Tests of shearfit.io.psfinput: given PSF images and PSFEx models.

The PSFEx reader is checked three ways: analytically (synthetic files whose
basis planes are delta functions, so the image shows each polynomial term's
value and position), against analytic Gaussians (the resampling geometry),
and against GalSim's independent reader ``galsim.des.DES_PSFEx`` on a real
DECam model.
"""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import galsim
import galsim.des

from shearfit.errors import ShearfitError, ShearfitIOError, ShearfitKeyError, ShearfitValueError
from shearfit.io.psfinput import PSFExModel, is_psfex_file, read_psf_fits, resample_matrix

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

# At its own sample points a Lanczos-3 InterpolatedImage returns the samples
# (the kernel is 1 at 0 and 0 at the other integers), so GalSim and the
# native PSFEx grid differ only by float32 arithmetic: measured 1.4e-7 of the
# peak. Evaluating the polynomial one pixel off (a 0-/1-based slip) already
# changes the image by 6e-5 of the peak.
NATIVE_TOL = 1e-6
# Off the sample points both interpolate with Lanczos-3 but correct its DC
# ripple differently (GalSim's conserve_dc vs our per-row normalisation):
# measured 4e-6 of the peak; without any DC correction it would be 4e-4.
RESAMPLED_TOL = 2e-5
# Our default band-limited (sinc) resampling against GalSim's Lanczos-3: the
# difference is Lanczos-3's attenuation below Nyquist, measured 6.4e-3 of the
# peak on this PSF (FWHM 4.6 pixels, 0.98 pixel samples), with the sinc
# image 0.3 % smaller in adaptive-moment size.
SINC_VS_GALSIM_TOL = 1e-2


def _real_psfex():
    path = REAL / "decam_00154912_12_psfex.psf"
    if not path.exists():
        pytest.skip(f"real data not available: {path}")
    return path


def write_psfex(path, mask, *, degree=2, zero=(100.0, 200.0), scale=(200.0, 400.0), samp=1.0,
                names=("X_IMAGE", "Y_IMAGE"), polnaxis=2):
    """A minimal PSFEx .psf file with the keywords PSFEx writes."""
    mask = np.asarray(mask, dtype=np.float32)
    n, ny, nx = mask.shape
    col = fits.Column(name="PSF_MASK", format=f"{mask.size}E", dim=f"({nx}, {ny}, {n})", array=mask[None])
    tab = fits.BinTableHDU.from_columns([col], name="PSF_DATA")
    hdr = tab.header
    hdr["POLNAXIS"] = polnaxis
    if polnaxis:
        for i in (1, 2):
            hdr[f"POLGRP{i}"] = 1
            hdr[f"POLNAME{i}"] = names[i - 1]
            hdr[f"POLZERO{i}"] = zero[i - 1]
            hdr[f"POLSCAL{i}"] = scale[i - 1]
        hdr["POLNGRP"] = 1
        hdr["POLDEG1"] = degree
    hdr["PSF_SAMP"] = samp
    hdr["PSFNAXIS"] = 3
    hdr["PSFAXIS1"], hdr["PSFAXIS2"], hdr["PSFAXIS3"] = nx, ny, n
    fits.HDUList([fits.PrimaryHDU(), tab]).writeto(path)
    return path


def _gaussian(n, step, sigma):
    t = (np.arange(n) - n // 2) * step
    g = np.exp(-0.5 * (t / sigma) ** 2)
    return np.outer(g, g)


# ------------------------------------------------------------------ PSFEx, analytic

def test_psfex_term_order_and_one_based_positions(tmp_path):
    # Plane t is a delta at pixel (0, t) plus, in the constant plane only, a
    # delta at the centre: the image then reads out every term's value.
    d = 2
    terms = [(i, j) for j in range(d + 1) for i in range(d + 1 - j)]  # 1, x, x^2, y, xy, y^2
    mask = np.zeros((len(terms), 25, 25))
    mask[0, 12, 12] = 1.0
    for t in range(len(terms)):
        mask[t, 0, t] = 1.0
    path = write_psfex(tmp_path / "delta.psf", mask, degree=d, zero=(100.0, 200.0), scale=(200.0, 400.0))
    m = PSFExModel(path)
    assert not m.needs_resampling and m.oversampling == 1
    x, y = 199.0, 299.0                      # 0-based: X_IMAGE = 200, Y_IMAGE = 300
    xi, eta = (200.0 - 100.0) / 200.0, (300.0 - 200.0) / 400.0
    img, k = m.image_at(x, y)
    assert k == 1 and img.shape == (25, 25)
    assert img.sum() == pytest.approx(1.0, abs=1e-12)
    for t, (i, j) in enumerate(terms):
        assert img[0, t] / img[12, 12] == pytest.approx(xi**i * eta**j, rel=1e-6), (t, i, j)


def test_psfex_constant_model(tmp_path):
    g = _gaussian(21, 1.0, 1.5)
    path = write_psfex(tmp_path / "const.psf", g[None] * 7.0, polnaxis=0)
    m = PSFExModel(path)
    a = m.image_at(10.0, 20.0).image
    b = m.image_at(3000.0, 5.0).image
    np.testing.assert_allclose(a, g / g.sum(), rtol=1e-6)
    np.testing.assert_array_equal(a, b)


def test_psfex_integer_oversampling_is_not_resampled(tmp_path):
    g = _gaussian(41, 0.5, 1.2)
    path = write_psfex(tmp_path / "over2.psf", np.stack([g] + [np.zeros_like(g)] * 5), samp=0.5)
    m = PSFExModel(path)
    img, k = m.image_at(500.0, 500.0)
    assert k == 2 and img.shape == (41, 41)
    np.testing.assert_allclose(img, g / g.sum(), rtol=1e-6)


# Largest |error| / peak allowed against an analytic Gaussian, and centroid
# error in output pixels. Sinc interpolation is exact for a band-limited
# function: what remains is the Gaussian's truncation at 6 sigma (1e-8), its
# spectrum beyond Nyquist (< 1e-13) and the file's float32 storage (6e-8):
# measured 2-3e-8. Lanczos-3 attenuates frequencies below Nyquist: measured
# 3-7e-3 of the peak and up to 2e-3 pixel.
GEOMETRY_TOL = {"sinc": (1e-6, 1e-6), "lanczos3": (1e-2, 5e-3)}


@pytest.mark.parametrize("interpolant", ["sinc", "lanczos3"])
@pytest.mark.parametrize("samp,sigma", [(0.8, 2.0), (0.6, 1.5), (1.1, 2.5), (0.97556, 1.95)])
def test_psfex_resampling_geometry(tmp_path, samp, sigma, interpolant):
    """A Gaussian tabulated every `samp` pixels comes back on the 1/k grid, centred on n // 2."""
    n = 31
    # Off-centre by fractions of a pixel so that a centring or scale error shows.
    cx, cy = 0.3, 0.1
    t = (np.arange(n) - n // 2) * samp
    g = np.outer(np.exp(-0.5 * ((t - cy) / sigma) ** 2), np.exp(-0.5 * ((t - cx) / sigma) ** 2))
    path = write_psfex(tmp_path / "g.psf", np.stack([g] + [np.zeros_like(g)] * 5), samp=samp)
    m = PSFExModel(path, interpolant=interpolant)
    img, k = m.image_at(0.0, 0.0)
    assert m.needs_resampling
    assert k == max(1, round(1.0 / samp))
    ny, nx = img.shape
    assert (ny, nx) == m.shape and ny % 2 == 1 and nx % 2 == 1
    tx = (np.arange(nx) - nx // 2) / k
    ty = (np.arange(ny) - ny // 2) / k
    expected = np.outer(np.exp(-0.5 * ((ty - cy) / sigma) ** 2), np.exp(-0.5 * ((tx - cx) / sigma) ** 2))
    expected /= expected.sum()
    value_tol, centre_tol = GEOMETRY_TOL[interpolant]
    assert np.max(np.abs(img - expected)) < value_tol * expected.max()
    yy, xx = np.mgrid[:ny, :nx]
    assert (img * xx).sum() == pytest.approx(nx // 2 + cx * k, abs=centre_tol)
    assert (img * yy).sum() == pytest.approx(ny // 2 + cy * k, abs=centre_tol)


def test_resample_matrix():
    # Lanczos-3 keeps a constant a constant away from the edges ...
    W = resample_matrix(41, 0.7, 25, 1.0, "lanczos3")
    inner = np.abs((np.arange(25) - 12) * 1.0) < (20 - 3) * 0.7
    np.testing.assert_allclose(W[inner].sum(axis=1), 1.0, atol=1e-12)
    # ... and both kernels only copy samples where the grids coincide
    # (output sample j sits on input sample 2j).
    for interpolant in ("sinc", "lanczos3"):
        W1 = resample_matrix(21, 0.5, 11, 1.0, interpolant)
        np.testing.assert_allclose(W1, np.eye(21)[::2], rtol=0, atol=1e-15)
    with pytest.raises(ShearfitValueError, match="lanczos3"):
        resample_matrix(5, 1.0, 5, 1.0, "cubic")


# ------------------------------------------------------------------ PSFEx, against GalSim

POSITIONS = [(0.0, 0.0), (1023.5, 2047.5), (2047.0, 4095.0), (300.2, 3900.7), (1800.0, 100.0)]


def test_real_psfex_native_grid_matches_galsim():
    path = _real_psfex()
    m = PSFExModel(path)
    ref = galsim.des.DES_PSFEx(str(path))
    assert m.basis.shape == (6, 25, 25) and m.degree == 2
    for x, y in POSITIONS:
        mine = m.native_image_at(x, y)
        # GalSim positions are 1-based; drawn with no extra pixel on a grid
        # whose pixels are the PSFEx samples, centred (odd size) on index 12.
        prof = ref.getPSF(galsim.PositionD(x + 1.0, y + 1.0))
        theirs = prof.drawImage(nx=25, ny=25, scale=m.psf_samp, method="no_pixel").array
        theirs = theirs / theirs.sum()
        assert np.max(np.abs(mine - theirs)) < NATIVE_TOL * mine.max(), (x, y)


@pytest.mark.parametrize("interpolant", ["lanczos3", "sinc"])
def test_real_psfex_image_grid_matches_galsim(interpolant):
    path = _real_psfex()
    m = PSFExModel(path, interpolant=interpolant)
    ref = galsim.des.DES_PSFEx(str(path))
    # PSF_SAMP = 0.9756: not 1/integer, so the model is resampled onto pixels.
    assert m.needs_resampling and m.oversampling == 1
    tol = RESAMPLED_TOL if interpolant == "lanczos3" else SINC_VS_GALSIM_TOL
    yy, xx = np.mgrid[:23, :23]
    for x, y in POSITIONS:
        img, k = m.image_at(x, y)
        assert k == 1
        assert img.shape == (23, 23)
        assert img.sum() == pytest.approx(1.0, abs=1e-12)
        prof = ref.getPSF(galsim.PositionD(x + 1.0, y + 1.0))
        theirs = prof.drawImage(nx=img.shape[1], ny=img.shape[0], scale=1.0, method="no_pixel").array
        theirs = theirs / theirs.sum()
        assert np.max(np.abs(img - theirs)) < tol * img.max(), (x, y)
        # Centred on (ny // 2, nx // 2) to a small fraction of a pixel.
        assert abs((img * xx).sum() - 11) < 0.2 and abs((img * yy).sum() - 11) < 0.2


def test_is_psfex_file(tmp_path):
    p = tmp_path / "img.fits"
    fits.PrimaryHDU(np.ones((5, 5))).writeto(p)
    assert not is_psfex_file(p)
    assert not is_psfex_file(tmp_path / "missing.psf")
    q = write_psfex(tmp_path / "m.psf", np.ones((6, 5, 5)))
    assert is_psfex_file(q)


def test_psfex_errors(tmp_path):
    with pytest.raises(ShearfitIOError, match="does not exist"):
        PSFExModel(tmp_path / "nope.psf")
    p = tmp_path / "img.fits"
    fits.PrimaryHDU(np.ones((5, 5))).writeto(p)
    with pytest.raises(ShearfitKeyError, match="PSF_DATA"):
        PSFExModel(p)
    q = write_psfex(tmp_path / "mag.psf", np.ones((6, 5, 5)), names=("X_IMAGE", "MAG_AUTO"))
    with pytest.raises(ShearfitValueError, match="X_IMAGE"):
        PSFExModel(q)
    r = write_psfex(tmp_path / "deg.psf", np.ones((4, 5, 5)), degree=2)
    with pytest.raises(ShearfitValueError, match="planes"):
        PSFExModel(r)


# ------------------------------------------------------------------ FITS PSF images

def test_read_psf_fits(tmp_path):
    g = _gaussian(33, 1.0 / 3, 2.0) * 5.0
    hdu = fits.ImageHDU(g, name="CCD1")
    hdu.header["OVERSAMP"] = 3
    path = tmp_path / "psf.fits"
    fits.HDUList([fits.PrimaryHDU(_gaussian(15, 1.0, 1.0)), hdu]).writeto(path)
    img, k = read_psf_fits(path, "CCD1")
    assert k == 3 and img.shape == (33, 33)
    assert img.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(img, g / g.sum(), rtol=1e-12)
    assert not img.flags.writeable
    img0, k0 = read_psf_fits(path, 0)
    assert k0 == 1 and img0.shape == (15, 15)
    np.testing.assert_array_equal(read_psf_fits(path, 1).image, img)


def _one_line_error(exc_info, *fragments):
    msg = str(exc_info.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, (f, msg)
    assert isinstance(exc_info.value, ShearfitError)


def test_read_psf_fits_errors(tmp_path):
    missing = tmp_path / "missing.fits"
    with pytest.raises(ShearfitIOError) as ei:
        read_psf_fits(missing, 0)
    _one_line_error(ei, "missing.fits", "does not exist")
    assert isinstance(ei.value, OSError)

    text = tmp_path / "notes.fits"
    text.write_text("this is not a FITS file\nat all\n")
    with pytest.raises(ShearfitIOError) as ei:
        read_psf_fits(text, 0)
    _one_line_error(ei, "notes.fits", "FITS")

    cube = tmp_path / "cube.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.ones((3, 9, 9)), name="PSF")]).writeto(cube)
    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(cube, "PSF")
    _one_line_error(ei, "cube.fits", "'PSF'", "2D", "(3, 9, 9)")
    assert isinstance(ei.value, ValueError)

    zero = tmp_path / "zero.fits"
    z = np.zeros((9, 9))
    z[4, 3], z[4, 5] = 1.0, -1.0
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(z)]).writeto(zero)
    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(zero, 1)
    _one_line_error(ei, "zero.fits", "HDU 1", "positive sum")

    with pytest.raises(ShearfitKeyError) as ei:
        read_psf_fits(zero, 5)
    _one_line_error(ei, "zero.fits", "no HDU 5")
    with pytest.raises(ShearfitKeyError) as ei:
        read_psf_fits(zero, "CCD9")
    _one_line_error(ei, "zero.fits", "'CCD9'")

    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(zero, 0)                      # empty primary HDU
    _one_line_error(ei, "zero.fits", "HDU 0", "no data")

    nan = tmp_path / "nan.fits"
    a = np.ones((9, 9))
    a[2, 2] = np.nan
    fits.PrimaryHDU(a).writeto(nan)
    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(nan, 0)
    _one_line_error(ei, "nan.fits", "non-finite")

    bad_k = tmp_path / "badk.fits"
    h = fits.PrimaryHDU(np.ones((9, 9)))
    h.header["OVERSAMP"] = 1.5
    h.writeto(bad_k)
    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(bad_k, 0)
    _one_line_error(ei, "badk.fits", "OVERSAMP")

    table = tmp_path / "table.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(
        [fits.Column(name="a", format="E", array=np.ones(3))])]).writeto(table)
    with pytest.raises(ShearfitValueError) as ei:
        read_psf_fits(table, 1)
    _one_line_error(ei, "table.fits", "not an image")


# ------------------------------------------------------------------ PSF moments over a CCD

def test_psf_moments_on_a_ccd_grid_match_hsm_at_each_object():
    """A PSF that varies over the CCD (the real DECam PSFEx model, g2 about -0.15, varying as a quadratic over a
    2048 x 4096 CCD): the pipeline's adaptive moments interpolated from a 7 x 7 grid of HSM measurements
    (``psf_moment_grid``) against HSM at each object. Measured: 4.3e-6 in sigma (relative), 1.2e-6 and 3.7e-6 in
    g1 and g2 (a 5 x 5 grid: 2.3e-5); the splines read with x and y swapped are off by 0.02-0.09."""
    from shearfit.pipeline.driver import _ExposurePSF, psf_moments

    model = PSFExModel(_real_psfex())
    epsf = _ExposurePSF(psfex=[model])
    shape = (4096, 2048)
    rng = np.random.default_rng(3)
    for x, y in zip(rng.uniform(0, 2047, 20), rng.uniform(0, 4095, 20)):
        psf = model.image_at(x, y)[0]
        direct = psf_moments(psf, epsf.sigma_guess(0, shape))
        sigma, (g1, g2) = epsf.moments_at(0, shape, x, y, psf, grid=7)
        assert abs(sigma / direct[0] - 1) < 2e-5
        assert abs(g1 - direct[1][0]) < 2e-5 and abs(g2 - direct[1][1]) < 2e-5
        # grid 0: HSM at the object itself
        assert epsf.moments_at(0, shape, x, y, psf, grid=0) == direct
    assert len(epsf._moment_splines) == 1   # one grid for the CCD, made once


def test_a_chunks_psf_moments_are_those_of_one_object_at_a_time(monkeypatch):
    """The pipeline evaluates the moments' splines for all of a chunk's objects on a CCD at once
    (``_chunk_geometry``): the same numbers as object by object (:meth:`_ExposurePSF.moments_at`)."""
    from types import SimpleNamespace

    from shearfit.pipeline.driver import _ExposurePSF, _chunk_geometry

    model = PSFExModel(_real_psfex())
    epsf = _ExposurePSF(psfex=[model])
    wcs = SimpleNamespace()   # no fitted model: the Jacobians are not needed here
    ccd = SimpleNamespace(wcs=wcs, shape=(4096, 2048))
    hits = [[(0, 0, 10.0, 20.0)], [(0, 0, 1500.25, 3000.75)], [(0, 0, 2047.0, 0.0)]]
    monkeypatch.setattr("shearfit.pipeline.driver.local_jacobian", lambda w, x, y: np.zeros((np.size(x), 2, 2)))
    geo = _chunk_geometry([([ccd], epsf)], hits, moment_grid=7)
    assert len(geo) == 3
    for (e, c, x, y), (_, _, _, _, mom) in geo.items():
        assert mom == epsf.moments_at(0, ccd.shape, x, y, model.image_at(x, y)[0], grid=7)


def test_psf_moment_grid_setting_is_checked():
    from shearfit.io.fieldconfig import PipelineConfig

    with pytest.raises(ShearfitValueError, match="psf_moment_grid"):
        PipelineConfig(psf_moment_grid=3)
    assert PipelineConfig(psf_moment_grid=0).psf_moment_grid == 0
