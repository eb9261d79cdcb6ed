"""Postage stamps (paper sec. 3.6, 4): exact centring and offsets, edges, and finding objects on CCDs."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from shearfit.errors import ShearfitValueError
from shearfit.io.fits import read_exposure
from shearfit.io.stamps import Stamp, cut_stamp, locate, locate_all

PIXEL_SCALE = 0.187 / 3600.0


def ramp(shape=(100, 80)):
    """An image whose every pixel value encodes its own (y, x): value = 1000 y + x."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    return (1000.0 * y + x).astype(np.float32)


# --- cut_stamp ------------------------------------------------------------------------

def test_stamp_centre_and_offset_exact():
    image = ramp()
    weight = np.full(image.shape, 0.5)
    st = cut_stamp(image, weight, 10.3, 20.7, 48)
    assert isinstance(st, Stamp)
    stamp, wstamp, offset, bounds = st  # unpacks as documented
    # Nearest pixel to (x, y) = (10.3, 20.7) is column 10, row 21; it sits at index (24, 24).
    assert st.centre == (21, 10)
    assert stamp[24, 24] == 1000 * 21 + 10
    assert offset == pytest.approx((0.3, -0.3), abs=1e-12)
    assert bounds == (21 - 24, 21 + 24, 10 - 24, 10 + 24)
    # No interpolation: every on-CCD stamp pixel is a CCD pixel, shifted by an integer.
    yy, xx = np.mgrid[:48, :48]
    on = (yy + bounds[0] >= 0) & (xx + bounds[2] >= 0)
    np.testing.assert_array_equal(stamp[on], (1000.0 * (yy + bounds[0]) + xx + bounds[2])[on])
    assert stamp.dtype == np.float64 and wstamp.dtype == np.float64


@pytest.mark.parametrize("size", [7, 8])
def test_stamp_centre_index_is_size_over_two(size):
    image = ramp()
    st = cut_stamp(image, 1.0, 40.0, 50.0, size)
    assert st.image.shape == (size, size)
    assert st.image[size // 2, size // 2] == 1000 * 50 + 40
    assert st.offset == (0.0, 0.0)


@pytest.mark.parametrize("x, ix", [(10.5, 11), (11.5, 12), (10.49, 10), (-0.5, 0), (79.49, 79)])
def test_stamp_rounds_halves_up(x, ix):
    st = cut_stamp(ramp(), 1.0, x, 50.0, 8)
    assert st.centre == (50, ix)
    assert st.offset[0] == pytest.approx(x - ix)
    assert -0.5 <= st.offset[0] < 0.5


def test_edge_stamp_has_zero_weight_outside():
    image = ramp()
    ny, nx = image.shape
    weight = np.full(image.shape, 2.0)
    st = cut_stamp(image, weight, 1.2, ny - 2.0, 16)   # near the left and top edges
    iy, ix = st.centre
    assert (iy, ix) == (ny - 2, 1)
    y0, y1, x0, x1 = st.bounds
    yy, xx = np.mgrid[y0:y1, x0:x1]
    on = (yy >= 0) & (yy < ny) & (xx >= 0) & (xx < nx)
    assert (~on).sum() > 0 and on.sum() > 0
    assert np.all(st.weight[~on] == 0) and np.all(st.image[~on] == 0)
    assert np.all(st.weight[on] == 2.0)
    np.testing.assert_array_equal(st.image[on], (1000.0 * yy + xx)[on])


def test_scalar_weight_and_nonfinite_pixels():
    image = ramp()
    image[50, 40] = np.nan
    image[51, 40] = np.inf
    st = cut_stamp(image, 0.25, 40.0, 50.0, 10)
    c = 5
    assert st.image[c, c] == 0 and st.weight[c, c] == 0
    assert st.image[c + 1, c] == 0 and st.weight[c + 1, c] == 0
    assert np.all(np.isfinite(st.image))
    assert (st.weight == 0.25).sum() == 98


@pytest.mark.parametrize("x, y", [(-0.51, 10.0), (79.5, 10.0), (10.0, -0.6), (10.0, 99.5), (np.nan, 3.0),
                                  (1e6, 1e6)])
def test_object_off_the_ccd_gives_none(x, y):
    assert cut_stamp(ramp(), 1.0, x, y, 16) is None


def test_stamp_argument_errors():
    image = ramp()
    with pytest.raises(ShearfitValueError, match="weight shape"):
        cut_stamp(image, np.ones((3, 3)), 10.0, 10.0, 8)
    with pytest.raises(ShearfitValueError, match="non-negative weight"):
        cut_stamp(image, -1.0, 10.0, 10.0, 8)
    with pytest.raises(ShearfitValueError, match="stamp size"):
        cut_stamp(image, 1.0, 10.0, 10.0, 0)


def test_stamp_does_not_change_the_ccd():
    image = ramp()
    image.flags.writeable = False  # as read_exposure hands it over
    weight = np.ones(image.shape)
    weight.flags.writeable = False
    st = cut_stamp(image, weight, 5.0, 5.0, 16)
    st.image[:] = -1
    assert image[5, 5] == 5005


# --- locate ---------------------------------------------------------------------------

class FakeCCD:
    def __init__(self, wcs, shape):
        self.wcs, self.shape = wcs, shape


def tan_wcs(crval, crpix, rotation_deg=0.0, scale=PIXEL_SCALE):
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = crval
    w.wcs.crpix = crpix
    c, s = np.cos(np.radians(rotation_deg)), np.sin(np.radians(rotation_deg))
    w.wcs.cd = scale * np.array([[-c, s], [s, c]])
    return w


def write_two_ccd_exposure(tmp_path, shape=(80, 60), overlap=5):
    """Two CCDs whose pixel areas overlap by ``overlap`` columns, so objects there are on both."""
    rng = np.random.default_rng(0)
    hdus = [fits.PrimaryHDU()]
    for k, crpix1 in enumerate([30.0, 30.0 - (shape[1] - overlap)]):
        h = tan_wcs((150.0, 2.0), (crpix1, 40.0)).to_header()
        h["MAGZP"], h["GAIN"], h["SATURATE"] = 30.0, 1.0, 6e4
        hdus.append(fits.ImageHDU(rng.normal(size=shape).astype(np.float32), header=h))
    fits.HDUList(hdus).writeto(tmp_path / "exp.fits")
    weights = [fits.PrimaryHDU()] + [fits.ImageHDU(np.ones(shape, np.float32)) for _ in range(2)]
    fits.HDUList(weights).writeto(tmp_path / "exp.weight.fits")
    return read_exposure(tmp_path / "exp.fits", tmp_path / "exp.weight.fits")


def test_locate_finds_the_right_ccds(tmp_path):
    ccds = write_two_ccd_exposure(tmp_path)
    w0 = ccds[0].wcs
    # Objects placed by pixel position on CCD 0 (x = column): the second CCD starts 55 columns to the
    # right (east is left: its RA is smaller), so x0 = 57 is at x1 = 2 on CCD 1.
    pix0 = np.array([[10.3, 20.7], [57.0, 40.0], [-3.0, 40.0], [30.0, -10.0], [100.0, 40.0]])
    ra, dec = w0.all_pix2world(pix0[:, 0], pix0[:, 1], 0)
    ra = np.append(ra, 200.0)   # nowhere near
    dec = np.append(dec, -30.0)
    found = locate([*ccds], ra, dec)
    assert [[c for c, _, _ in f] for f in found] == [[0], [0, 1], [], [], [1], []]
    c, x, y = found[0][0]
    assert (x, y) == pytest.approx((10.3, 20.7), abs=1e-6)
    (c0, x0, y0), (c1, x1, y1) = found[1]
    assert (x0, y0) == pytest.approx((57.0, 40.0), abs=1e-6)
    assert (x1, y1) == pytest.approx((2.0, 40.0), abs=1e-6)
    assert (found[4][0][1], found[4][0][2]) == pytest.approx((45.0, 40.0), abs=1e-6)
    # A single object gives its own list.
    one = locate(ccds, float(ra[1]), float(dec[1]))
    assert [c for c, _, _ in one] == [0, 1]
    assert locate(ccds, 200.0, -30.0) == []
    # The pixels locate() reports are those cut_stamp() needs.
    st = cut_stamp(ccds[1].image, ccds[1].weight, x1, y1, 8)
    assert st.centre == (40, 2)


def test_locate_pixel_area_edges(tmp_path):
    ccds = write_two_ccd_exposure(tmp_path, overlap=0)
    w0 = ccds[0].wcs
    ny, nx = ccds[0].shape
    # Just inside and just outside the pixel area [-0.5, n - 0.5) of CCD 0, away from CCD 1's side.
    pix = np.array([[5.0, -0.49], [5.0, -0.51], [5.0, ny - 0.51], [5.0, ny - 0.49], [-0.49, 10.0],
                    [-0.51, 10.0]])
    ra, dec = w0.all_pix2world(pix[:, 0], pix[:, 1], 0)
    found = locate(ccds, ra, dec)
    assert [[c for c, _, _ in f] for f in found] == [[0], [], [0], [], [0], []]


def test_locate_vectorised_matches_brute_force():
    # A 3 x 2 mosaic near RA = 0 (the prefilter must not care about the wrap), rotated by 30 degrees.
    shape = (200, 100)
    ccds = []
    for i in range(3):
        for j in range(2):
            w = tan_wcs((0.01, -30.0), (50.0 - 105 * i, 100.0 - 205 * j), rotation_deg=30.0)
            ccds.append(FakeCCD(w, shape))
    rng = np.random.default_rng(42)
    n = 20000
    ra = (0.01 + rng.uniform(-0.03, 0.03, n) / np.cos(np.radians(30.0))) % 360.0
    dec = -30.0 + rng.uniform(-0.03, 0.03, n)
    loc = locate_all(ccds, ra, dec)

    expected = []
    for k, ccd in enumerate(ccds):
        x, y = ccd.wcs.all_world2pix(ra, dec, 0)
        inside = (x >= -0.5) & (x < shape[1] - 0.5) & (y >= -0.5) & (y < shape[0] - 0.5)
        expected += [(i, k) for i in np.flatnonzero(inside)]
    expected.sort()
    assert len(expected) > 1000  # the test must exercise the mosaic
    assert list(zip(loc.object.tolist(), loc.ccd.tolist())) == expected
    for k in range(len(ccds)):
        sel = loc.ccd == k
        x, y = ccds[k].wcs.all_world2pix(ra[loc.object[sel]], dec[loc.object[sel]], 0)
        np.testing.assert_allclose(loc.x[sel], x, atol=1e-9)
        np.testing.assert_allclose(loc.y[sel], y, atol=1e-9)


def test_locate_near_the_pole_and_empty_inputs():
    ccd = FakeCCD(tan_wcs((123.0, 89.995), (50.5, 50.5)), (100, 100))
    # Objects around the pole: the CCD spans all RAs within ~0.01 deg of its centre.
    ra = np.array([0.0, 90.0, 180.0, 270.0, 10.0])
    dec = np.array([89.9955, 89.9955, 89.9955, 89.9955, 89.9])
    found = locate([ccd], ra, dec)
    for f, (r, d) in zip(found, zip(ra, dec)):
        x, y = ccd.wcs.all_world2pix(r, d, 0)
        on = -0.5 <= x < 99.5 and -0.5 <= y < 99.5
        assert [c for c, _, _ in f] == ([0] if on else [])
    assert sum(len(f) for f in found) >= 1
    assert locate([ccd], np.zeros(0), np.zeros(0)) == []
    assert locate([], np.array([1.0]), np.array([2.0])) == [[]]
    assert locate([ccd], np.array([np.nan]), np.array([2.0])) == [[]]
