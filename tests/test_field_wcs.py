"""Tests of shearfit.io.wcs: the local Jacobian d(u, v)/d(x, y) from a WCS (sec. 6).

Two independent references:

* finite differences computed here, through a different route from the
  library's: a 5-point stencil (error O(h^4), exact for the cubic TPV/SIP
  polynomials) of ``all_pix2world`` projected onto the tangent plane with
  unit vectors (p . e_west / p . r0, p . e_north / p . r0) instead of the
  library's trigonometric gnomonic formulas;
* GalSim's ``GSFitsWCS(header).jacobian(PositionD(x + 1, y + 1))``: its own
  TAN/TPV/SIP implementation, 1-based positions, 1-pixel centred differences
  of (ra, dec), u = -dRA cos(dec) (GalSim's +u is west).

Errors are quoted relative to the local pixel scale sqrt|det J|, since the
off-diagonal terms of a north-up Jacobian are near zero.
"""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

import galsim

from shearfit.errors import ShearfitValueError
from shearfit.io.wcs import (as_wcs, header_from_ldac, local_jacobian, pixel_to_sky,
                                sky_to_pixel, tangent_plane_offsets)

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

# The requirement for the agreement with finite differences of the WCS.
FD_RTOL = 1e-6
# GalSim differences with a 1-pixel step: truncation h^2 f'''/6 measures ~5e-10
# of the pixel scale on the DECam TPV header, rounding of (ra, dec) in degrees
# ~2e-10; the two TPV implementations agree on positions to ~1e-10 arcsec.
# Measured: 4-6e-10 on the real headers, 1.4e-9 on the SIP and TAN headers.
# 1e-8 leaves a margin while still catching any sign, axis or 0-/1-based
# slip (evaluating GalSim one pixel off changes J by 2e-6 to 2e-5 here).
GALSIM_RTOL = 1e-8


def _real(name):
    path = REAL / name
    if not path.exists():
        pytest.skip(f"real data not available: {path}")
    return path


def decam_header():
    return fits.getheader(_real("decam_00154912_12_header.fits"), 0)


def ldac_header():
    with fits.open(_real("decam_00241238_01_stars.fits")) as hdul:
        return header_from_ldac(hdul["LDAC_IMHEAD"])


def mosaic_header():
    return fits.getheader(_real("mosaic2_tpv.fits"), 0)


# (header factory, image size nx, ny): the DECam primary header is header-only
# (NAXIS1 = 0); its CCD is 2048 x 4096 (DATASEC).
REAL_HEADERS = {
    "decam_header": (decam_header, 2048, 4096),
    "decam_ldac": (ldac_header, 2048, 4096),
    "mosaic2": (mosaic_header, 512, 512),
}


def _positions(nx, ny, n=20, seed=0):
    rng = np.random.default_rng(seed)
    x = np.concatenate([[0.0, nx - 1.0, 0.0, nx - 1.0], rng.uniform(0, nx - 1, n - 4)])
    y = np.concatenate([[0.0, 0.0, ny - 1.0, ny - 1.0], rng.uniform(0, ny - 1, n - 4)])
    return x, y


def _unit(ra, dec):
    a, d = np.radians(ra), np.radians(dec)
    return np.stack([np.cos(d) * np.cos(a), np.cos(d) * np.sin(a), np.sin(d)], axis=-1)


def reference_jacobian(wcs, x, y, h=1.0):
    """Independent J: 5-point stencil, unit-vector gnomonic projection about the object."""
    ra0, dec0 = wcs.all_pix2world([x], [y], 0)
    r0 = _unit(ra0[0], dec0[0])
    a, d = np.radians(ra0[0]), np.radians(dec0[0])
    east = np.array([-np.sin(a), np.cos(a), 0.0])
    north = np.array([-np.sin(d) * np.cos(a), -np.sin(d) * np.sin(a), np.cos(d)])
    steps = np.array([-2.0, -1.0, 1.0, 2.0]) * h
    coef = np.array([1.0, -8.0, 8.0, -1.0]) / (12.0 * h)
    J = np.empty((2, 2))
    for col, (dx, dy) in enumerate([(1.0, 0.0), (0.0, 1.0)]):
        ra, dec = wcs.all_pix2world(x + dx * steps, y + dy * steps, 0)
        p = _unit(ra, dec)
        proj = p @ r0
        u = -(p @ east) / proj
        v = (p @ north) / proj
        J[0, col] = coef @ u
        J[1, col] = coef @ v
    return J * (180.0 / np.pi * 3600.0)


def galsim_jacobian(header, x, y):
    gw = galsim.GSFitsWCS(header=header)
    return gw.jacobian(galsim.PositionD(x + 1.0, y + 1.0)).getMatrix()  # GalSim is 1-based


def _rel(J, Jref):
    scale = np.sqrt(abs(np.linalg.det(Jref)))
    return np.max(np.abs(J - Jref)) / scale


# ------------------------------------------------------------------ real headers

def _real_header(name):
    """A real header of ../shared/data/real/, its astropy WCS and test positions over its CCD."""
    factory, nx, ny = REAL_HEADERS[name]
    header = factory()
    x, y = _positions(nx, ny)
    return header, as_wcs(header), x, y


@pytest.mark.parametrize("name", sorted(REAL_HEADERS))
def test_real_tpv_jacobian_matches_finite_differences_and_galsim(name):
    header, w, x, y = _real_header(name)
    J = local_jacobian(w, x, y)
    assert J.shape == (x.size, 2, 2)
    worst_fd = worst_gs = 0.0
    for i in range(x.size):
        worst_fd = max(worst_fd, _rel(J[i], reference_jacobian(w, x[i], y[i])))
        worst_gs = max(worst_gs, _rel(J[i], galsim_jacobian(header, x[i], y[i])))
    assert worst_fd < FD_RTOL, worst_fd
    assert worst_gs < GALSIM_RTOL, worst_gs
    # A sane pixel scale (DECam 0.263", Mosaic-II 0.26").
    scale = np.sqrt(np.abs(np.linalg.det(J)))
    assert np.all((scale > 0.2) & (scale < 0.3))


@pytest.mark.parametrize("name", sorted(REAL_HEADERS))
def test_real_tpv_distortion_is_applied(name):
    """astropy must apply the TPV polynomial (PVi_j), and agree with GalSim's TPV code."""
    header, w, x, y = _real_header(name)
    ra, dec = pixel_to_sky(w, x, y)
    gw = galsim.GSFitsWCS(header=header)
    for i in range(x.size):
        c = gw.toWorld(galsim.PositionD(x[i] + 1.0, y[i] + 1.0))
        du, dv = tangent_plane_offsets(c.ra.deg, c.dec.deg, ra[i], dec[i])
        assert np.hypot(du, dv) < 1e-6  # arcsec
    # The same header with the PV terms dropped (plain TAN) maps elsewhere and
    # has a different Jacobian: the distortion is really there.
    plain = header.copy()
    plain["CTYPE1"], plain["CTYPE2"] = "RA---TAN", "DEC--TAN"
    for key in [k for k in plain.keys() if k.startswith("PV")]:
        del plain[key]
    J_tpv = local_jacobian(w, x, y)
    J_tan = local_jacobian(as_wcs(plain), x, y)
    assert np.max(np.abs(J_tpv - J_tan)) / 0.26 > 1e-3


def test_header_from_ldac():
    h = ldac_header()
    assert h["NAXIS1"] == 2048 and h["NAXIS2"] == 4096
    assert h["CTYPE1"].startswith("RA---TPV")
    assert "PV1_1" in h


# ------------------------------------------------------------------ synthetic TAN

def tan_header(scale=0.2, angle_deg=0.0, flip=False, ra=150.0, dec=2.0, crpix=(1000.5, 1500.5)):
    """TAN header whose pixel grid is rotated by angle (from north, through east) and maybe mirrored.

    The CD matrix maps (dx, dy) to intermediate world coordinates (xi east, eta
    north) in degrees. With u = -xi (west), v = eta:  J = diag(-1, 1) CD * 3600.
    """
    s = scale / 3600.0
    c, t = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    # North-up, east-left (CD1_1 < 0) rotated by the angle ...
    cd = s * np.array([[-c, t], [t, c]])
    if flip:  # ... or its mirror image: east to the right.
        cd = cd @ np.diag([-1.0, 1.0])
    h = fits.Header()
    h["NAXIS"] = 2
    h["NAXIS1"], h["NAXIS2"] = 2000, 3000
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = ra, dec
    h["CRPIX1"], h["CRPIX2"] = crpix
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1]
    return h, cd


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, 137.0, 250.0])
@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("ra,dec", [(150.0, 2.0), (0.0, -45.0), (359.99, 80.0)])
def test_tan_rotation_and_flip(angle, flip, ra, dec):
    h, cd = tan_header(angle_deg=angle, flip=flip, ra=ra, dec=dec)
    w = as_wcs(h)
    # At the reference pixel the object's tangent plane is the TAN plane itself.
    x0, y0 = h["CRPIX1"] - 1.0, h["CRPIX2"] - 1.0
    expected = np.diag([-1.0, 1.0]) @ cd * 3600.0
    J = local_jacobian(w, x0, y0)
    assert J.shape == (2, 2)
    # Rounding of (ra, dec) limits this to ~1e-9 of the scale (see local_jacobian).
    np.testing.assert_allclose(J, expected, rtol=0, atol=1e-8 * 0.2)
    # J is scale x (rotation, or rotation x mirror): orthogonal up to the scale.
    np.testing.assert_allclose(J @ J.T / 0.2**2, np.eye(2), atol=1e-8)
    assert np.sign(np.linalg.det(J)) == (-1.0 if flip else 1.0)
    # Elsewhere (the frame turns with the local meridian) against GalSim and
    # the independent finite differences.
    for x, y in [(0.0, 0.0), (1999.0, 2999.0), (250.3, 2700.8)]:
        J = local_jacobian(w, x, y)
        assert _rel(J, reference_jacobian(w, x, y)) < FD_RTOL
        assert _rel(J, galsim_jacobian(h, x, y)) < GALSIM_RTOL


def test_north_up_east_left_is_the_uv_frame():
    """docs/interface.rst: CD1_1 < 0, north up: +x is west, +y north, so J = diag(s, s)."""
    h, _ = tan_header(scale=0.187, angle_deg=0.0, flip=False, ra=35.0, dec=-5.0)
    J = local_jacobian(h, h["CRPIX1"] - 1.0, h["CRPIX2"] - 1.0)
    np.testing.assert_allclose(J, np.diag([0.187, 0.187]), rtol=0, atol=1e-8 * 0.187)
    # Moving +x lowers the RA (west), moving +y raises the Dec (north).
    ra0, dec0 = pixel_to_sky(h, 999.5, 1499.5)
    ra1, _ = pixel_to_sky(h, 1009.5, 1499.5)
    _, dec1 = pixel_to_sky(h, 999.5, 1509.5)
    assert ra1 < ra0 and dec1 > dec0


# ------------------------------------------------------------------ SIP

def sip_header():
    h, _ = tan_header(scale=0.2, angle_deg=20.0, ra=210.0, dec=54.0, crpix=(1024.5, 1024.5))
    h["NAXIS1"], h["NAXIS2"] = 2048, 2048
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN-SIP", "DEC--TAN-SIP"
    h["A_ORDER"] = h["B_ORDER"] = 3
    # Gradients of ~2-4 per cent at the corners (|x|, |y| ~ 1000 pixels).
    h["A_2_0"], h["A_1_1"], h["A_0_2"] = 1.0e-5, -6.0e-6, 4.0e-6
    h["A_3_0"], h["A_1_2"] = 5.0e-9, -3.0e-9
    h["B_2_0"], h["B_1_1"], h["B_0_2"] = -5.0e-6, 8.0e-6, 1.2e-5
    h["B_0_3"], h["B_2_1"] = 4.0e-9, 2.0e-9
    return h


def test_sip_jacobian():
    h = sip_header()
    w = as_wcs(h)
    assert w.sip is not None
    x, y = _positions(2048, 2048, n=12, seed=3)
    J = local_jacobian(w, x, y)
    worst_fd = max(_rel(J[i], reference_jacobian(w, x[i], y[i])) for i in range(x.size))
    worst_gs = max(_rel(J[i], galsim_jacobian(h, x[i], y[i])) for i in range(x.size))
    assert worst_fd < FD_RTOL, worst_fd
    assert worst_gs < GALSIM_RTOL, worst_gs
    # The distortion is of order a few per cent at the corners.
    plain = WCS(naxis=2)
    plain.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    plain.wcs.crval = [h["CRVAL1"], h["CRVAL2"]]
    plain.wcs.crpix = [h["CRPIX1"], h["CRPIX2"]]
    plain.wcs.cd = [[h["CD1_1"], h["CD1_2"]], [h["CD2_1"], h["CD2_2"]]]
    J0 = local_jacobian(plain, x, y)
    dist = np.max(np.abs(J - J0), axis=(1, 2)) / 0.2
    assert 0.01 < dist.max() < 0.1


# ------------------------------------------------------------------ API behaviour

def test_vectorised_equals_loop():
    h = decam_header() if (REAL / "decam_00154912_12_header.fits").exists() else sip_header()
    w = as_wcs(h)
    rng = np.random.default_rng(7)
    x = rng.uniform(0, 2047, (4, 5))
    y = rng.uniform(0, 2047, (4, 5))
    J = local_jacobian(w, x, y)
    assert J.shape == (4, 5, 2, 2)
    for idx in np.ndindex(4, 5):
        np.testing.assert_allclose(J[idx], local_jacobian(w, x[idx], y[idx]), rtol=1e-13, atol=0)
    ra, dec = pixel_to_sky(w, x, y)
    assert ra.shape == (4, 5)
    for idx in np.ndindex(4, 5):
        r1, d1 = pixel_to_sky(w, x[idx], y[idx])
        assert isinstance(r1, float)
        assert r1 == pytest.approx(ra[idx], abs=1e-12) and d1 == pytest.approx(dec[idx], abs=1e-12)


def test_explicit_centre_equals_default():
    h = sip_header()
    x, y = np.array([10.0, 1500.0]), np.array([2000.0, 33.0])
    ra, dec = pixel_to_sky(h, x, y)
    np.testing.assert_allclose(local_jacobian(h, x, y, ra0=ra, dec0=dec), local_jacobian(h, x, y),
                               rtol=0, atol=1e-12)
    # A centre far away turns the frame (convergence of meridians) but keeps the area.
    Jf = local_jacobian(h, x, y, ra0=h["CRVAL1"] + 2.0, dec0=h["CRVAL2"])
    J = local_jacobian(h, x, y)
    assert np.max(np.abs(Jf - J)) > 1e-3
    with pytest.raises(ShearfitValueError):
        local_jacobian(h, x, y, ra0=1.0)


def test_sky_pixel_round_trip():
    for h in [sip_header()] + ([mosaic_header()] if (REAL / "mosaic2_tpv.fits").exists() else []):
        w = as_wcs(h)
        x, y = _positions(500, 500, n=30, seed=5)
        ra, dec = pixel_to_sky(w, x, y)
        x2, y2 = sky_to_pixel(w, ra, dec)
        np.testing.assert_allclose(x2, x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(y2, y, rtol=0, atol=1e-6)
    # Where the iterative inverse of a strong distortion fails, NaN, not an exception.
    h, _ = tan_header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN-SIP", "DEC--TAN-SIP"
    h["A_ORDER"] = h["B_ORDER"] = 2
    h["A_2_0"] = h["B_0_2"] = 1e-3
    x, y = sky_to_pixel(h, [150.0, 170.0], [2.0, -10.0])
    assert x[0] == pytest.approx(999.5, abs=1e-6) and y[0] == pytest.approx(1499.5, abs=1e-6)
    assert np.isnan(x[1]) and np.isnan(y[1])


def test_tangent_plane_offsets_match_galsim_project():
    rng = np.random.default_rng(11)
    for ra0, dec0 in [(104.3, -55.9), (0.001, 10.0), (359.999, -89.0), (200.0, 89.5)]:
        ra = ra0 + rng.normal(0, 0.5, 8)
        dec = np.clip(dec0 + rng.normal(0, 0.3, 8), -89.99, 89.99)
        u, v = tangent_plane_offsets(ra % 360.0, dec, ra0, dec0)
        c0 = galsim.CelestialCoord(ra0 * galsim.degrees, dec0 * galsim.degrees)
        for i in range(ra.size):
            c = galsim.CelestialCoord((ra[i] % 360.0) * galsim.degrees, dec[i] * galsim.degrees)
            gu, gv = c0.project(c, projection="gnomonic")
            assert u[i] == pytest.approx(gu / galsim.arcsec, abs=1e-8)
            assert v[i] == pytest.approx(gv / galsim.arcsec, abs=1e-8)
    # +u is west: a point at larger RA (east) has u < 0; north has v > 0.
    u, v = tangent_plane_offsets(10.001, 0.0, 10.0, 0.0)
    assert u == pytest.approx(-3.6, rel=1e-6) and abs(v) < 1e-9
    u, v = tangent_plane_offsets(10.0, 0.001, 10.0, 0.0)
    assert v == pytest.approx(3.6, rel=1e-6) and abs(u) < 1e-9
    # The far hemisphere has no gnomonic image.
    u, v = tangent_plane_offsets(190.0, 0.0, 10.0, 0.0)
    assert np.isnan(u) and np.isnan(v)


def test_bad_wcs_inputs():
    h = fits.Header()
    h["NAXIS"] = 2
    h["CTYPE1"], h["CTYPE2"] = "LINEAR", "LINEAR"
    with pytest.raises(ShearfitValueError, match="celestial"):
        local_jacobian(h, 1.0, 1.0)
    swapped, _ = tan_header()
    for a, b in [("CTYPE1", "CTYPE2"), ("CRVAL1", "CRVAL2")]:
        swapped[a], swapped[b] = swapped[b], swapped[a]
    with pytest.raises(ShearfitValueError, match="order"):
        as_wcs(swapped)
    with pytest.raises(ShearfitValueError):
        as_wcs("not a wcs")
    with pytest.raises(ShearfitValueError):
        local_jacobian(tan_header()[0], 1.0, 1.0, h=0.0)
