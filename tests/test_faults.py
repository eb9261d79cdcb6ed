"""Real survey inputs and their faults: compressed and scaled-integer files, bad rows, unusable exposures.

A fault in one catalogue row, CCD or exposure costs that row, CCD or exposure (a fitclass code, or a
warning naming the file and HDU), not the run; a fault that makes the whole run meaningless (duplicate
ids, a given PSF that does not match its exposure) is a one-line error that leaves no output behind.

The pipeline runs measure a handful of galaxies of the ``tiny`` simulated field (3 exposures of one
CCD each) and compare, bit for bit, with a run on inputs that hold the same values in plain files.
"""

import logging
import mmap
import os

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import MaskedColumn, Table

pytest.importorskip("galsim")

from test_field_io import ccd_header, one_line, two_ccd_exposure, write_mef  # noqa: E402

from shearfit.errors import (FITCLASS_BAD_INPUT, FITCLASS_OFF_EXPOSURES, ShearfitValueError)  # noqa: E402
from shearfit.io.fieldconfig import load_field_config  # noqa: E402
from shearfit.io.fits import (HDUPixels, attach_pixels, detached, read_catalog, read_exposure,  # noqa: E402
                              release_pages)
from shearfit.io.psfinput import psf_image_hdus, read_psf_fits  # noqa: E402
from shearfit.io.stamps import cut_stamp  # noqa: E402
from shearfit.pipeline import driver  # noqa: E402
from shearfit.simulate.field import simulate_field, simulation_config  # noqa: E402

# galaxies of the tiny field (seed 11) that lie on all three exposures, away from blends
ROWS = [0, 1, 2, 12, 13, 14]
LOSSLESS = dict(compression_type="GZIP_2", quantize_level=0)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("faults")
    simulate_field(simulation_config({"preset": "tiny", "seed": 11}), d)
    Table.read(d / "objects.fits")[ROWS].write(d / "few.fits")
    return d


def _specs(n=3, **files):
    """Exposure entries of the tiny field (given PSFs), with some files replaced: ``image1="x.fits"``."""
    specs = []
    for k in range(n):
        s = {"image": f"exp{k}.fits", "weight": f"exp{k}.weight.fits", "psf": f"exp{k}.psf.fits"}
        for key in ("image", "weight", "psf"):
            if f"{key}{k}" in files:
                s[key] = files[f"{key}{k}"]
        specs.append({key: v for key, v in s.items() if v is not None})
    return specs


def _measure(d, out, specs, catalog="few.fits", **settings):
    conf = {"exposures": specs, "catalog": catalog, "psf_min_stars": 8, "psf_order": 1, **settings}
    path = d / f"{os.path.basename(str(out))}.yaml"
    path.write_text(yaml.safe_dump(conf))
    return driver.measure_field(load_field_config(path), out_path=str(out))


def _same(a, b, rows=None):
    for c in b.colnames:
        x = np.asarray(a[c]) if rows is None else np.asarray(a[c])[rows]
        y = np.asarray(b[c])
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), c


@pytest.fixture(scope="module")
def reference(field, tmp_path_factory):
    """The handful of galaxies measured on the plain files."""
    return _measure(field, tmp_path_factory.mktemp("ref") / "ref.fits", _specs())


def _mapped(a):
    """Whether an array is a view of a memory map (what release_pages releases)."""
    while a is not None and not isinstance(a, mmap.mmap):
        a = getattr(a, "base", None)
    return a is not None


def _compress(src, dst, **kw):
    """``src`` tile-compressed as fpack writes it: an empty primary HDU, one CompImageHDU per image HDU."""
    with fits.open(src) as h:
        hdus = [fits.PrimaryHDU(header=h[0].header if h[0].data is None else None)]
        for hdu in h:
            if hdu.data is not None:
                hdus.append(fits.CompImageHDU(hdu.data, header=hdu.header, **(kw or LOSSLESS)))
        fits.HDUList(hdus).writeto(dst)
    return str(dst)


def _scaled(src, dst, bscale=0.05, bzero=10.0):
    """``src`` as 16-bit integers with BSCALE/BZERO (values beyond the range clipped)."""
    with fits.open(src) as h:
        hdus = [fits.PrimaryHDU(header=h[0].header)]
        for hdu in h[1:]:
            q = np.clip(np.round((hdu.data - bzero) / bscale), -32768, 32767).astype(np.int16)
            out = fits.ImageHDU(q, header=hdu.header)
            out.header["BSCALE"], out.header["BZERO"] = bscale, bzero
            hdus.append(out)
        fits.HDUList(hdus).writeto(dst)
    return str(dst)


# --- A: compressed and scaled-integer inputs, read ----------------------------------------------

def test_compressed_image_and_weight_read_as_the_floats(tmp_path):
    image_path, weight_path, images = two_ccd_exposure(tmp_path)
    cimage = _compress(image_path, tmp_path / "exp.fits.fz")
    cweight = _compress(weight_path, tmp_path / "exp.weight.fits.fz")
    plain = read_exposure(image_path, weight_path)
    ccds = read_exposure(cimage, cweight)
    assert [c.hdu for c in ccds] == [1, 2] and [c.extname for c in ccds] == ["CCD1", "CCD2"]
    for a, b in zip(ccds, plain):
        # not memory-mapped, read on demand; lossless compression gives the very floats back
        assert isinstance(a.image, HDUPixels) and isinstance(a.weight, HDUPixels)
        assert a.image.shape == b.image.shape == (80, 60) and a.image.dtype == np.float32
        np.testing.assert_array_equal(np.asarray(a.image), b.image)
        np.testing.assert_array_equal(np.asarray(a.weight), b.weight)
        assert (a.magzp, a.gain, a.saturate) == (b.magzp, b.gain, b.saturate) and a.usable
        sa, sb = cut_stamp(a.image, a.pixel_weight, 3.2, 70.6, 16), cut_stamp(b.image, b.pixel_weight, 3.2, 70.6, 16)
        np.testing.assert_array_equal(sa.image, sb.image)
        np.testing.assert_array_equal(sa.weight, sb.weight)
        assert not a.image[2:5, 1:4].flags.writeable
    # the chunks' path: detached, attached again, pages released (nothing to release, and no failure)
    again = attach_pixels(detached(ccds))
    release_pages(again)
    for a, b in zip(again, plain):
        np.testing.assert_array_equal(np.asarray(a.image), b.image)
        np.testing.assert_array_equal(a.weight[10:20, ::7], b.weight[10:20, ::7])
    # without a weight file the noise is estimated from the decompressed pixels, as from the floats
    assert read_exposure(cimage)[1].noise_ivar == read_exposure(image_path)[1].noise_ivar
    # plain floats stay memory-mapped
    assert _mapped(plain[0].image) and _mapped(plain[0].weight)
    assert not _mapped(ccds[0].image) and not _mapped(again[0].weight)


def test_scaled_integer_image_reads_as_the_scaled_values(tmp_path):
    image_path, weight_path, images = two_ccd_exposure(tmp_path)
    spath = _scaled(image_path, tmp_path / "scaled.fits")
    with fits.open(spath) as h:
        assert h[1].header["BITPIX"] == 16 and h[1].header["BSCALE"] == 0.05 and h[1].header["BZERO"] == 10.0
    # memory-mapped, astropy cannot give these pixels at all
    with fits.open(spath, memmap=True) as h, pytest.raises(ValueError, match="memory-mapped"):
        h[1].data
    with fits.open(spath, memmap=False) as h:
        expected = [h[i].data.copy() for i in (1, 2)]
    ccds = read_exposure(spath, weight_path)
    again = attach_pixels(detached(ccds))
    release_pages(again)
    for c, a, want, orig in zip(ccds, again, expected, images):
        assert isinstance(c.image, HDUPixels) and c.image.dtype == np.float32
        np.testing.assert_array_equal(np.asarray(c.image), want)
        np.testing.assert_array_equal(np.asarray(a.image), want)
        # to the precision the format allows: half a BSCALE
        assert np.max(np.abs(np.asarray(c.image) - orig)) <= 0.025 + 1e-5
        st = cut_stamp(c.image, c.pixel_weight, 30.0, 40.0, 12)
        np.testing.assert_array_equal(st.image, want[34:46, 24:36].astype(np.float64))


def test_given_psf_compressed_or_scaled(tmp_path):
    y, x = np.mgrid[:25, :25] - 12
    psfs = [np.exp(-(x**2 + y**2) / (2 * s**2)) for s in (1.5, 2.5)]
    psfs = [p / p.sum() for p in psfs]
    plain = tmp_path / "plain.psf.fits"
    fits.HDUList([fits.PrimaryHDU()] + [fits.ImageHDU(p) for p in psfs]).writeto(plain)
    packed = _compress(plain, tmp_path / "packed.psf.fits.fz")
    scaled = tmp_path / "scaled.psf.fits"
    hdus = [fits.PrimaryHDU()]
    for p in psfs:
        h = fits.ImageHDU(np.round(p / 1e-6).astype(np.int32))
        h.header["BSCALE"], h.header["BZERO"] = 1e-6, 0.0
        hdus.append(h)
    fits.HDUList(hdus).writeto(scaled)
    for path in (plain, packed, scaled):
        assert psf_image_hdus(path) == [1, 2], path
    for k, p in enumerate(psfs):
        np.testing.assert_array_equal(read_psf_fits(packed, k + 1).image, read_psf_fits(plain, k + 1).image)
        got = read_psf_fits(scaled, k + 1).image
        np.testing.assert_allclose(got, p, atol=2e-6)
        assert got.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("kind", ["compressed image", "compressed weight", "compressed psf", "scaled image"])
def test_pipeline_measures_compressed_and_scaled_inputs(field, reference, tmp_path, kind):
    d = field
    if kind == "compressed image":
        specs = _specs(**{f"image{k}": _compress(d / f"exp{k}.fits", tmp_path / f"exp{k}.fits.fz") for k in range(3)})
    elif kind == "compressed weight":
        specs = _specs(**{f"weight{k}": _compress(d / f"exp{k}.weight.fits", tmp_path / f"exp{k}.weight.fits.fz")
                          for k in range(3)})
    elif kind == "compressed psf":
        specs = _specs(**{f"psf{k}": _compress(d / f"exp{k}.psf.fits", tmp_path / f"exp{k}.psf.fits.fz")
                          for k in range(3)})
    else:
        specs = _specs(image1=_scaled(d / "exp1.fits", tmp_path / "exp1.int16.fits", bscale=0.02, bzero=0.0))
    t = _measure(d, tmp_path / "shear.fits", specs)
    assert np.sum(t["fitclass"] == 0) >= 4
    if kind != "scaled image":
        # lossless: the same pixels, the same catalogue bit for bit
        _same(t, reference)
        return
    # the same catalogue as from plain floats holding the scaled values
    with fits.open(tmp_path / "exp1.int16.fits", memmap=False) as h:
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(h[1].data.astype(np.float32), header=h[1].header)]) \
            .writeto(tmp_path / "exp1.dequantised.fits")
    with fits.open(tmp_path / "exp1.dequantised.fits") as h:
        assert "BSCALE" not in h[1].header and h[1].header["BITPIX"] == -32
    plain = _measure(d, tmp_path / "plain.fits", _specs(image1=str(tmp_path / "exp1.dequantised.fits")))
    _same(t, plain)


# --- B1: bad catalogue rows ---------------------------------------------------------------------

def test_bad_catalogue_rows_cost_only_their_row(field, reference, tmp_path, caplog):
    d = field
    cat = Table.read(d / "few.fits")
    n = len(cat)
    ra0, dec0 = float(cat["ra"][0]), float(cat["dec"][0])
    extra = [(900, np.nan, dec0, 22.0), (901, ra0, np.inf, 22.0), (902, ra0, dec0, np.nan),
             (903, ra0, dec0, -np.inf), (904, ra0 + 1.0, dec0, 22.0), (905, ra0, 95.0, 22.0)]
    for row in extra:
        cat.add_row(row)
    # a masked (null) magnitude too
    cat["mag"] = MaskedColumn(cat["mag"], mask=np.zeros(len(cat), bool))
    cat.add_row((906, ra0, dec0, 0.0), mask=[False, False, False, True])
    cat.write(d / "bad_rows.fits", overwrite=True)
    with caplog.at_level(logging.WARNING, logger="shearfit.pipeline.driver"):
        t = _measure(d, tmp_path / "shear.fits", _specs(), catalog="bad_rows.fits")
    assert list(t["id"]) == list(cat["id"])   # every row, in input order
    _same(t[:n], reference)                   # the good rows as if the bad ones were not there
    fc = dict(zip(t["id"][n:], t["fitclass"][n:]))
    assert fc == {900: FITCLASS_BAD_INPUT, 901: FITCLASS_BAD_INPUT, 902: FITCLASS_BAD_INPUT,
                  903: FITCLASS_BAD_INPUT, 904: FITCLASS_OFF_EXPOSURES, 905: FITCLASS_BAD_INPUT,
                  906: FITCLASS_BAD_INPUT}
    assert np.all(t["weight"][n:] == 0) and np.all(np.isnan(t["e1"][n:])) and np.all(t["n_exposures_used"][n:] == 0)
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    path = str(d / "bad_rows.fits")
    for col, rows in (("ra", f"({n})"), ("dec", f"({n + 1}, {n + 5})"), ("mag", f"({n + 2}, {n + 3}, {n + 6})")):
        assert any(path in m and f"column {col!r}" in m and rows in m and "\n" not in m for m in msgs), (col, msgs)
    # the strict reader (the star catalogue, the API) still refuses such a file, in one line
    with pytest.raises(ShearfitValueError) as exc:
        read_catalog(d / "bad_rows.fits")
    assert path in one_line(exc) and "'ra'" in str(exc.value)


def test_duplicate_ids_stop_the_run_before_any_work(field, tmp_path, monkeypatch):
    d = field
    cat = Table.read(d / "few.fits")
    cat["id"][3] = cat["id"][1]
    cat["id"][5] = cat["id"][4]
    cat.write(d / "dup.fits", overwrite=True)

    def no_work(*args, **kwargs):
        raise AssertionError("an exposure was read before the catalogue was checked")

    monkeypatch.setattr(driver, "read_exposure", no_work)
    out = tmp_path / "shear.fits"
    with pytest.raises(ShearfitValueError) as exc:
        _measure(d, out, _specs(), catalog="dup.fits")
    msg = one_line(exc)
    a, b = int(cat["id"][1]), int(cat["id"][4])
    assert str(d / "dup.fits") in msg and "column 'id'" in msg
    assert f"duplicate id {a}" in msg and "rows 1 and 3" in msg and f"{a}, {b}" in msg
    assert not out.exists() and not os.path.exists(str(out) + ".parts")
    assert [f for f in os.listdir(tmp_path) if not f.endswith(".yaml")] == []


# --- B2: unusable CCDs and exposures ------------------------------------------------------------

def test_read_exposure_skips_a_ccd_without_wcs_and_marks_one_without_pixels(tmp_path, caplog):
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    with fits.open(image_path, mode="update") as h:
        for key in ("CTYPE1", "CTYPE2"):
            del h[1].header[key]
    with pytest.raises(ShearfitValueError):
        read_exposure(image_path, weight_path)                 # the API's default: an error
    with caplog.at_level(logging.WARNING, logger="shearfit.io.fits"):
        ccds = read_exposure(image_path, weight_path, skip_unusable=True)
    assert [c.hdu for c in ccds] == [2] and ccds[0].ccd_index == 1 and ccds[0].n_file_ccds == 2
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(msgs) == 1 and image_path in msgs[0] and "HDU 1" in msgs[0] and "left out" in msgs[0]

    caplog.clear()
    with fits.open(weight_path, mode="update") as h:
        h[2].data[:] = 0.0
    with caplog.at_level(logging.WARNING, logger="shearfit.io.fits"):
        ccds = read_exposure(image_path, weight_path, skip_unusable=True)
    assert len(ccds) == 1 and not ccds[0].usable
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(weight_path in m and "HDU 2" in m and "every weight" in m for m in msgs), msgs

    # no weight file and nothing to estimate the noise from: marked, not an error
    flat = write_mef(tmp_path / "flat.fits", [np.zeros((20, 20)), np.ones((20, 20)) * np.arange(20)],
                     [ccd_header(), ccd_header()])
    ccds = read_exposure(flat, skip_unusable=True)
    assert [c.usable for c in ccds] == [False, True] and ccds[0].noise_ivar == 0.0


def _two_ccd_copy(d, k, tmp_path):
    """Exposure k as two CCD HDUs: HDU 1 without a WCS (and a wrong, wide PSF), HDU 2 the real CCD."""
    with fits.open(d / f"exp{k}.fits") as h, fits.open(d / f"exp{k}.weight.fits") as w, \
            fits.open(d / f"exp{k}.psf.fits") as p:
        bad = h[1].header.copy()
        for key in ("CTYPE1", "CTYPE2"):
            del bad[key]
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(h[1].data, header=bad, name="NOWCS"),
                      fits.ImageHDU(h[1].data, header=h[1].header, name="CCD")]).writeto(tmp_path / "two.fits")
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(w[1].data), fits.ImageHDU(w[1].data)]) \
            .writeto(tmp_path / "two.weight.fits")
        y, x = np.mgrid[:144, :144] - 72
        wide = np.exp(-(x**2 + y**2) / (2 * 20.0**2))
        ph = fits.ImageHDU(wide / wide.sum())
        ph.header["OVERSAMP"] = 3
        fits.HDUList([fits.PrimaryHDU(), ph, p[1].copy()]).writeto(tmp_path / "two.psf.fits")
    return {f"image{k}": str(tmp_path / "two.fits"), f"weight{k}": str(tmp_path / "two.weight.fits"),
            f"psf{k}": str(tmp_path / "two.psf.fits")}


def test_ccd_without_wcs_is_left_out(field, reference, tmp_path, caplog):
    d = field
    with caplog.at_level(logging.WARNING):
        t = _measure(d, tmp_path / "shear.fits", _specs(**_two_ccd_copy(d, 0, tmp_path)))
    # the other CCD is measured with its own PSF (HDU 2 of the PSF file, not HDU 1): the same catalogue
    _same(t, reference)
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(tmp_path / "two.fits") in m and "HDU 1 (NOWCS)" in m and "no celestial WCS" in m
               and "left out" in m for m in msgs), msgs


@pytest.fixture(scope="module")
def two_exposures(field, tmp_path_factory):
    """The handful of galaxies measured on exposures 0 and 2 only, with given PSFs."""
    specs = _specs()
    return _measure(field, tmp_path_factory.mktemp("two") / "two.fits", [specs[0], specs[2]])


def test_exposure_with_zero_weights_is_left_out(field, two_exposures, tmp_path, caplog):
    d = field
    with fits.open(d / "exp1.weight.fits") as h:
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros_like(h[1].data), header=h[1].header)]) \
            .writeto(tmp_path / "exp1.zero.weight.fits")
    with caplog.at_level(logging.WARNING):
        t = _measure(d, tmp_path / "shear.fits", _specs(weight1=str(tmp_path / "exp1.zero.weight.fits")))
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(d / "exp1.fits") in m and str(tmp_path / "exp1.zero.weight.fits") in m and "HDU 1" in m
               and "every weight" in m and "left out" in m for m in msgs), msgs
    # the objects are measured on the other two exposures, as if the third had not been given
    assert np.all(t["n_exposures_used"] <= 2) and np.sum(t["fitclass"] == 0) >= 4
    _same(t, two_exposures)


def test_exposure_with_too_few_stars_is_left_out(field, tmp_path, caplog):
    d = field
    # exposure 1 without its stars (and galaxies): pure noise, so no star passes the cuts
    with fits.open(d / "exp1.fits") as h:
        noise = np.random.default_rng(3).normal(0.0, float(np.std(h[1].data[:40, :40])), h[1].data.shape)
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(noise.astype(np.float32), header=h[1].header)]) \
            .writeto(tmp_path / "exp1.nostars.fits")
    fitted = [{k: v for k, v in s.items() if k != "psf"} for s in _specs(image1=str(tmp_path / "exp1.nostars.fits"))]
    with caplog.at_level(logging.WARNING):
        t = _measure(d, tmp_path / "shear.fits", fitted, stars="stars.fits")
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("psf_min_stars" in m and str(tmp_path / "exp1.nostars.fits") in m and "HDU 1" in m
               and "left out" in m for m in msgs), msgs
    ref = _measure(d, tmp_path / "ref.fits", [fitted[0], fitted[2]], stars="stars.fits")
    assert np.all(t["n_exposures_used"] <= 2) and np.sum(t["fitclass"] == 0) >= 4
    _same(t, ref)


# --- B3: a given PSF that does not match its exposure --------------------------------------------

def test_given_psf_must_match_the_exposure(field, tmp_path):
    d = field
    with fits.open(d / "exp0.psf.fits") as p:
        fits.HDUList([fits.PrimaryHDU(), p[1].copy(), p[1].copy()]).writeto(tmp_path / "more.psf.fits")
    two = _two_ccd_copy(d, 0, tmp_path)
    cases = [(_specs(psf0=str(tmp_path / "more.psf.fits")), tmp_path / "more.psf.fits", d / "exp0.fits", 2, 1),
             (_specs(image0=two["image0"], weight0=two["weight0"]), d / "exp0.psf.fits", tmp_path / "two.fits", 1, 2)]
    for specs, psf, image, n_psf, n_ccd in cases:
        out = tmp_path / "shear.fits"
        with pytest.raises(ShearfitValueError) as exc:
            _measure(d, out, specs)
        msg = one_line(exc)
        assert str(psf) in msg and str(image) in msg
        assert f"has {n_psf} PSF image HDUs" in msg and f"has {n_ccd} CCDs" in msg
        assert not out.exists() and not os.path.exists(str(out) + ".parts")
