"""Reading a field's config, catalogues and exposures, and writing the shear catalogue.

Every error case checks that the message is one line and names what the user
must fix: the file, and the HDU, column or key.
"""

import json
import logging
import os

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from shearfit.config import FitConfig
from shearfit.errors import (FITCLASS_FIT_FAILED, FITCLASS_OFF_EXPOSURES, ShearfitError, ShearfitIOError,
                             ShearfitKeyError, ShearfitValueError)
from shearfit.io.fieldconfig import (FieldConfig, PipelineConfig, field_config_from_mapping,
                                        load_field_config)
from shearfit.io.stamps import cut_stamp
from shearfit.io.fits import (COMMON_ZEROPOINT, attach_pixels, detached, empty_output_table, empty_result_row,
                               estimate_noise,
                               output_columns, photometric_scale, provenance_cards, read_catalog,
                               read_exposure, write_catalog_atomic)

PIXEL_SCALE = 0.187 / 3600.0  # degrees per pixel, MegaCam's


def ccd_header(crpix=(30.0, 40.0), crval=(150.0, 2.0), magzp=30.5, gain=1.5, saturate=60000.0):
    """A CCD header with a TAN WCS, north up and east left (RA decreasing with x)."""
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRPIX1"], h["CRPIX2"] = crpix
    h["CRVAL1"], h["CRVAL2"] = crval
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = -PIXEL_SCALE, 0.0, 0.0, PIXEL_SCALE
    h["MAGZP"], h["GAIN"], h["SATURATE"] = magzp, gain, saturate
    return h


def write_mef(path, images, headers, primary_header=None):
    hdus = [fits.PrimaryHDU(header=primary_header)]
    for i, (img, hdr) in enumerate(zip(images, headers)):
        hdus.append(fits.ImageHDU(np.asarray(img, dtype=np.float32), header=hdr, name=f"CCD{i + 1}"))
    fits.HDUList(hdus).writeto(path)
    return str(path)


def two_ccd_exposure(tmp_path, shape=(80, 60), sigma=2.0, seed=1, with_weight=True, name="exp"):
    """Two CCDs side by side, with Gaussian noise of known sigma and an inverse-variance weight file."""
    rng = np.random.default_rng(seed)
    images = [rng.normal(0.0, sigma, shape) for _ in range(2)]
    headers = [ccd_header(crpix=(30.0, 40.0)), ccd_header(crpix=(30.0 - 70.0, 40.0), magzp=30.2)]
    image_path = write_mef(tmp_path / f"{name}.fits", images, headers)
    weight_path = None
    if with_weight:
        weights = [np.full(shape, 1.0 / sigma**2) for _ in range(2)]
        weight_path = write_mef(tmp_path / f"{name}.weight.fits", weights, [fits.Header(), fits.Header()])
    return image_path, weight_path, images


def write_catalog(path, columns):
    Table(columns).write(path)
    return str(path)


def one_line(exc_info):
    msg = str(exc_info.value)
    assert "\n" not in msg, msg
    return msg


# --- field config ------------------------------------------------------------------

def write_config(tmp_path, text, name="field.yaml", subdir="conf"):
    d = tmp_path / subdir
    d.mkdir(exist_ok=True)
    p = d / name
    p.write_text(text)
    return p


MINIMAL = """
exposures:
  - image: exp/000001.fits
    weight: exp/000001.weight.fits
    psf: exp/000001.psf.fits
  - image: exp/000002.fits
catalog: objects.fits
stars: ../stars.fits
output: shear.fits
"""


def test_config_resolves_paths_relative_to_the_config_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative to the file, not to where we run
    p = write_config(tmp_path, MINIMAL)
    cfg = load_field_config(p)
    base = str(tmp_path / "conf")
    assert cfg.exposures[0].image == os.path.join(base, "exp", "000001.fits")
    assert cfg.exposures[0].weight == os.path.join(base, "exp", "000001.weight.fits")
    assert cfg.exposures[0].psf == os.path.join(base, "exp", "000001.psf.fits")
    assert cfg.exposures[1].weight is None and cfg.exposures[1].psf is None
    assert cfg.catalog == os.path.join(base, "objects.fits")
    assert cfg.stars == str(tmp_path / "stars.fits")
    assert cfg.output == os.path.join(base, "shear.fits")
    assert cfg.fit == FitConfig()
    assert cfg.pipeline == PipelineConfig()
    assert cfg.pipeline.stamp_size == 48


def test_config_settings_go_to_their_component(tmp_path):
    p = write_config(tmp_path, MINIMAL + "stamp_size: 64\nneighbour_mask: false\nn_flux: 9\n"
                     "psf_mode_tolerance: 1e-5\nisophote_nsigma: 3\n")
    cfg = load_field_config(p)
    assert cfg.pipeline.stamp_size == 64
    assert cfg.pipeline.neighbour_mask is False
    assert cfg.pipeline.isophote_nsigma == 3.0 and isinstance(cfg.pipeline.isophote_nsigma, float)
    assert cfg.fit.n_flux == 9
    # PyYAML alone (YAML 1.1) would read 1e-5 as a string.
    assert cfg.fit.psf_mode_tolerance == 1e-5


def test_config_unknown_key_is_named_with_the_file(tmp_path):
    p = write_config(tmp_path, MINIMAL + "stamp_sise: 64\n")
    with pytest.raises(ShearfitKeyError) as exc:
        load_field_config(p)
    msg = one_line(exc)
    assert "'stamp_sise'" in msg and str(p) in msg and "stamp_size" in msg
    assert isinstance(exc.value, KeyError)


def test_config_unknown_exposure_key(tmp_path):
    p = write_config(tmp_path, "exposures:\n  - image: a.fits\n    wieght: w.fits\ncatalog: c.fits\n")
    with pytest.raises(ShearfitKeyError) as exc:
        load_field_config(p)
    msg = one_line(exc)
    assert "'wieght'" in msg and "exposures[0]" in msg and str(p) in msg


def _config_error(tmp_path, text, exc_type):
    """Write ``text`` as a config, load it expecting ``exc_type``: (path, one-line message)."""
    p = write_config(tmp_path, text)
    with pytest.raises(exc_type) as exc:
        load_field_config(p)
    return p, one_line(exc)


@pytest.mark.parametrize("text, key", [
    ("catalog: c.fits\n", "'exposures'"),
    ("exposures:\n  - weight: w.fits\ncatalog: c.fits\n", "exposures[0].image"),
    ("exposures:\n  - image: a.fits\n", "'catalog'"),
])
def test_config_missing_required_key(tmp_path, text, key):
    p, msg = _config_error(tmp_path, text, ShearfitKeyError)
    assert key in msg and "missing" in msg and str(p) in msg


@pytest.mark.parametrize("extra, key", [
    ("stamp_size: big\n", "stamp_size"),
    ("stamp_size: 48.5\n", "stamp_size"),
    ("neighbour_mask: 1\n", "neighbour_mask"),
    ("n_flux: eleven\n", "n_flux"),         # a FitConfig setting: its message gets the file too
    ("sigma_pop: -0.2\n", "sigma_pop"),
    ("stamp_size: 4\n", "stamp_size"),
])
def test_config_wrong_type_or_range_names_key_and_file(tmp_path, extra, key):
    p, msg = _config_error(tmp_path, MINIMAL + extra, ShearfitValueError)
    assert key in msg and str(p) in msg


@pytest.mark.parametrize("text, words", [
    ("exposures: exp.fits\ncatalog: c.fits\n", "exposures"),
    ("exposures:\n  - exp.fits\ncatalog: c.fits\n", "exposures[0]"),
    ("exposures:\n  - image: 3\ncatalog: c.fits\n", "exposures[0].image"),
    ("exposures:\n  - image: a.fits\ncatalog: [c.fits]\n", "catalog"),
    ("- a\n- b\n", "mapping"),
    ("", "empty"),
    ("exposures: [\n", "invalid YAML"),
    ("exposures:\n  - image: a.fits\ncatalog: c.fits\ncatalog: d.fits\n", "duplicate key 'catalog'"),
])
def test_config_malformed(tmp_path, text, words):
    p, msg = _config_error(tmp_path, text, ShearfitError)
    assert words in msg and str(p) in msg


def test_config_missing_file(tmp_path):
    with pytest.raises(ShearfitIOError) as exc:
        load_field_config(tmp_path / "nope.yaml")
    assert "nope.yaml" in one_line(exc)


def test_config_overrides(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = write_config(tmp_path, MINIMAL + "stamp_size: 32\n")
    cfg = load_field_config(p, ["stamp_size=64", "neighbour_mask=false", "sigma_pop=0.3",
                                "exposures.1.psf=here.psf.fits", "stars=", "output=/abs/out.fits"])
    assert cfg.pipeline.stamp_size == 64
    assert cfg.pipeline.neighbour_mask is False
    assert cfg.fit.sigma_pop == 0.3
    # A path typed on the command line is relative to where the command runs.
    assert cfg.exposures[1].psf == str(tmp_path / "here.psf.fits")
    assert cfg.stars is None
    assert cfg.output == os.path.normpath("/abs/out.fits")


@pytest.mark.parametrize("override, exc_type, words", [
    ("stamp_sise=64", ShearfitKeyError, "'stamp_sise'"),
    ("stamp_size", ShearfitValueError, "key=value"),
    ("stamp_size=[1,", ShearfitValueError, "invalid YAML"),
    ("exposures.5.psf=a.fits", ShearfitKeyError, "no exposure 5"),
    ("exposures.0.mask=a.fits", ShearfitKeyError, "'mask'"),
    ("fit.n_flux=3", ShearfitKeyError, "'fit'"),
])
def test_config_bad_overrides(tmp_path, override, exc_type, words):
    p = write_config(tmp_path, MINIMAL)
    with pytest.raises(exc_type) as exc:
        load_field_config(p, [override])
    msg = one_line(exc)
    assert words in msg and override in msg


def test_config_override_wrong_type(tmp_path):
    p = write_config(tmp_path, MINIMAL)
    with pytest.raises(ShearfitValueError) as exc:
        load_field_config(p, ["stamp_size=big"])
    assert "stamp_size" in one_line(exc)


def test_config_to_dict_round_trips(tmp_path):
    p = write_config(tmp_path, MINIMAL + "stamp_size: 40\nn_size: 5\n")
    cfg = load_field_config(p)
    d = cfg.to_dict()
    assert d["stamp_size"] == 40 and d["n_size"] == 5 and d["catalog"] == cfg.catalog
    json.dumps(d)  # provenance goes into a header as JSON
    again = field_config_from_mapping(d, base_dir="/somewhere/else", source=str(p))
    assert again == cfg
    assert isinstance(cfg, FieldConfig)


def test_config_check_files(tmp_path):
    p = write_config(tmp_path, MINIMAL)
    cfg = load_field_config(p)
    with pytest.raises(ShearfitIOError) as exc:
        cfg.check_files()
    msg = one_line(exc)
    assert "catalog" in msg and "objects.fits" in msg


# --- catalogues ---------------------------------------------------------------------

def test_read_catalog_matches_columns_without_case(tmp_path):
    path = write_catalog(tmp_path / "cat.fits", {"ID": [3, 1, 2], "Ra": [150.0, 150.001, 150.002],
                                                 "DEC": np.array([2.0, 2.001, 2.002], dtype=np.float32),
                                                 "MAG": [22.0, 23.0, 24.0], "extra": ["a", "b", "c"]})
    t = read_catalog(path)
    assert t.colnames[:4] == ["id", "ra", "dec", "mag"] and "extra" in t.colnames
    assert list(t["id"]) == [3, 1, 2]  # input order kept
    assert t["dec"].dtype == np.float64


@pytest.mark.parametrize("columns, exc_type, words", [
    ({"id": [1, 2], "ra": [1.0, 2.0], "dec": [1.0, 2.0]}, ShearfitKeyError, "no column 'mag'"),
    ({"id": [1, 2], "ra": [1.0, np.nan], "dec": [1.0, 2.0], "mag": [20.0, 21.0]}, ShearfitValueError,
     "'ra' is not finite"),
    ({"id": [1, 2], "ra": [1.0, 2.0], "dec": [1.0, np.inf], "mag": [20.0, 21.0]}, ShearfitValueError,
     "'dec' is not finite"),
    ({"id": [1, 2], "ra": [1.0, 2.0], "dec": [1.0, 95.0], "mag": [20.0, 21.0]}, ShearfitValueError,
     "[-90, 90]"),
    ({"id": [7, 5, 7], "ra": [1.0, 2.0, 3.0], "dec": [1.0, 2.0, 3.0], "mag": [20.0, 21.0, 22.0]},
     ShearfitValueError, "duplicate id 7"),
    ({"id": np.zeros(0, int), "ra": np.zeros(0), "dec": np.zeros(0), "mag": np.zeros(0)}, ShearfitValueError,
     "empty"),
    ({"id": [1], "ra": [1.0], "RA": [1.0], "dec": [1.0], "mag": [20.0]}, ShearfitValueError, "'RA'"),
    ({"id": [1], "ra": ["x"], "dec": [1.0], "mag": [20.0]}, ShearfitValueError, "'ra' must be numeric"),
])
def test_read_catalog_errors(tmp_path, columns, exc_type, words):
    path = write_catalog(tmp_path / "cat.fits", columns)
    with pytest.raises(exc_type) as exc:
        read_catalog(path)
    msg = one_line(exc)
    assert words in msg and path in msg and "HDU 1" in msg


def test_read_catalog_file_errors(tmp_path):
    with pytest.raises(ShearfitIOError) as exc:
        read_catalog(tmp_path / "missing.fits")
    assert "missing.fits" in one_line(exc) and "no such file" in str(exc.value)

    (tmp_path / "text.fits").write_text("id ra dec mag\n1 2 3 4\n")
    with pytest.raises(ShearfitIOError) as exc:
        read_catalog(tmp_path / "text.fits")
    assert "text.fits" in one_line(exc) and "not a readable FITS file" in str(exc.value)

    fits.PrimaryHDU(np.zeros((4, 4))).writeto(tmp_path / "image.fits")
    with pytest.raises(ShearfitValueError) as exc:
        read_catalog(tmp_path / "image.fits")
    assert "image.fits" in one_line(exc) and "no table HDU" in str(exc.value)


# --- exposures ----------------------------------------------------------------------

def test_read_exposure_two_ccds(tmp_path):
    image_path, weight_path, images = two_ccd_exposure(tmp_path)
    ccds = read_exposure(image_path, weight_path)
    assert len(ccds) == 2
    for k, ccd in enumerate(ccds):
        assert ccd.hdu == k + 1 and ccd.extname == f"CCD{k + 1}"
        assert ccd.shape == (80, 60)
        np.testing.assert_array_equal(ccd.image, images[k].astype(np.float32))
        np.testing.assert_allclose(ccd.weight, 0.25)
        assert not ccd.image.flags.writeable and not ccd.weight.flags.writeable
        assert ccd.gain == 1.5 and ccd.saturate == 60000.0
        assert ccd.wcs.has_celestial and ccd.n_bad_pixels == 0
        assert ccd.path == image_path and ccd.weight_path == weight_path
    assert ccds[0].magzp == 30.5 and ccds[1].magzp == 30.2
    assert ccds[1].flux_scale == pytest.approx(10 ** (0.4 * 0.2))
    # The WCS maps CRPIX (1-based in FITS) to CRVAL at 0-based pixel CRPIX - 1.
    x, y = ccds[0].wcs.all_world2pix(150.0, 2.0, 0)
    assert x == pytest.approx(29.0) and y == pytest.approx(39.0)


def test_read_exposure_primary_hdu_and_inherited_keywords(tmp_path):
    h = ccd_header()
    fits.PrimaryHDU(np.ones((10, 12), dtype=np.float32) * np.arange(12), header=h).writeto(tmp_path / "p.fits")
    ccds = read_exposure(tmp_path / "p.fits", None)
    assert len(ccds) == 1 and ccds[0].hdu == 0 and ccds[0].weight is None

    # Exposure-wide keywords in the primary header apply to every extension.
    prim = fits.Header()
    prim["MAGZP"], prim["GAIN"], prim["SATURATE"] = 29.0, 2.0, 50000.0
    hdr = ccd_header()
    for key in ("MAGZP", "GAIN", "SATURATE"):
        del hdr[key]
    rng = np.random.default_rng(3)
    path = write_mef(tmp_path / "inh.fits", [rng.normal(size=(20, 20))], [hdr], primary_header=prim)
    ccd, = read_exposure(path)
    assert (ccd.magzp, ccd.gain, ccd.saturate) == (29.0, 2.0, 50000.0)


def test_read_exposure_without_weight_estimates_constant_noise(tmp_path, caplog):
    sigma = 2.0
    image_path, _, images = two_ccd_exposure(tmp_path, shape=(200, 150), sigma=sigma, with_weight=False)
    with caplog.at_level(logging.INFO, logger="shearfit.io.fits"):
        ccds = read_exposure(image_path)
    assert any("no weight file" in r.getMessage() and image_path in r.getMessage() for r in caplog.records)
    for ccd in ccds:
        assert ccd.weight is None
        # 30000 pixels: the MAD's relative error is about 1.7/sqrt(N) ~ 1 %; allow 5 sigma.
        assert ccd.noise_ivar == pytest.approx(1 / sigma**2, rel=0.1)
        assert ccd.pixel_weight == ccd.noise_ivar


def test_estimate_noise_ignores_objects():
    rng = np.random.default_rng(5)
    image = rng.normal(0.0, 3.0, (300, 300))
    image[100:120, 100:120] += 500.0  # a bright object must not inflate the noise
    # 9e4 pixels; the sigma-clipped MAD has about 1.3 % relative error: 5 % is ~4 sigma.
    assert estimate_noise(image) == pytest.approx(3.0, rel=0.05)


def test_nan_pixels_get_zero_weight(tmp_path, caplog):
    image_path, weight_path, images = two_ccd_exposure(tmp_path)
    with fits.open(image_path, mode="update") as h:
        h[2].data[5, 7] = np.nan
        h[2].data[6, 7] = np.inf
    with caplog.at_level(logging.WARNING, logger="shearfit.io.fits"):
        ccds = read_exposure(image_path, weight_path)
    assert ccds[0].n_bad_pixels == 0 and ccds[1].n_bad_pixels == 2
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(msgs) == 1 and "HDU 2" in msgs[0] and " 2 " in msgs[0] and image_path in msgs[0]
    # the weight file stays as it is (memory-mapped); a stamp over the bad pixels weights them 0
    st = cut_stamp(ccds[1].image, ccds[1].pixel_weight, 7.0, 5.0, 8)
    iy, ix = st.image.shape[0] // 2, st.image.shape[1] // 2
    assert st.weight[iy, ix] == 0 and st.weight[iy + 1, ix] == 0 and st.weight[iy, ix + 1] == 0.25
    assert st.image[iy, ix] == 0

    # Without a weight file: the constant weight, and the stamp's zeros the same
    ccds = read_exposure(image_path)
    assert ccds[0].weight is None and ccds[1].weight is None and ccds[1].n_bad_pixels == 2
    st = cut_stamp(ccds[1].image, ccds[1].pixel_weight, 7.0, 5.0, 8)
    assert st.weight[iy, ix] == 0 and st.weight[iy + 1, ix] == 0
    assert st.weight[0, 0] == pytest.approx(ccds[1].noise_ivar)


def test_detached_ccds_attach_the_same_pixels(tmp_path):
    image_path, weight_path, images = two_ccd_exposure(tmp_path)
    ccds = read_exposure(image_path, weight_path)
    meta = detached(ccds)
    assert all(c.image is None and c.weight is None for c in meta)
    assert [c.shape for c in meta] == [c.shape for c in ccds]
    again = attach_pixels(meta)
    for a, b in zip(again, ccds):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.weight, b.weight)
        assert a.label == b.label and not a.image.flags.writeable
    # without a weight file: no weight, the estimated noise carried over
    again = attach_pixels(detached(read_exposure(image_path)))
    assert again[0].weight is None and again[0].noise_ivar > 0


def test_attached_wcs_is_parsed_once_per_file_version(tmp_path):
    """A process attaching a field's CCDs for chunk after chunk parses each WCS once; a file rewritten since
    (another size or modification time) is parsed again, and gives its new WCS."""
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    meta = detached(read_exposure(image_path, weight_path))
    first, second = attach_pixels(meta), attach_pixels(meta)
    assert all(a.wcs is b.wcs for a, b in zip(first, second))
    with fits.open(image_path) as h:
        h[1].header["CRVAL1"] = h[1].header["CRVAL1"] + 0.01
        h.writeto(image_path, overwrite=True)
    os.utime(image_path, ns=(os.stat(image_path).st_atime_ns, os.stat(image_path).st_mtime_ns + 10**9))
    third = attach_pixels(meta)
    assert third[0].wcs is not first[0].wcs
    assert third[0].wcs.wcs.crval[0] == pytest.approx(first[0].wcs.wcs.crval[0] + 0.01)


def test_pickled_detached_ccds_give_the_same_wcs_bit_for_bit(tmp_path):
    # a worker gets the CCDs pickled; astropy pickles a WCS through a header with fewer digits, so the
    # WCS must come from the file again or a worker's catalogue differs from one process's (at 1e-12)
    import pickle

    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    angle = np.radians(23.456789012345)
    cd = 0.187 / 3600 * np.array([[-np.cos(angle), np.sin(angle)], [np.sin(angle), np.cos(angle)]]) / 3.0
    with fits.open(image_path, mode="update") as h:
        for hdu in h[1:]:
            for key in ("CDELT1", "CDELT2", "PC1_1", "PC1_2", "PC2_1", "PC2_2"):
                hdu.header.remove(key, ignore_missing=True)
            hdu.header["CD1_1"], hdu.header["CD1_2"] = cd[0]
            hdu.header["CD2_1"], hdu.header["CD2_2"] = cd[1]
    ccds = read_exposure(image_path, weight_path)
    again = attach_pixels(pickle.loads(pickle.dumps(detached(ccds))))
    rng = np.random.default_rng(3)
    for a, b in zip(again, ccds):
        x, y = rng.uniform(0, 100, 50), rng.uniform(0, 100, 50)
        np.testing.assert_array_equal(np.array(a.wcs.all_pix2world(x, y, 0)), np.array(b.wcs.all_pix2world(x, y, 0)))
        np.testing.assert_array_equal(a.wcs.pixel_scale_matrix, b.wcs.pixel_scale_matrix)


def test_read_exposure_keeps_no_scanned_pixels_resident(tmp_path):
    # the NaN and weight checks read every pixel; they must not leave the pages in this process's memory
    shape = (4096, 2048)
    rng = np.random.default_rng(1)
    path = write_mef(tmp_path / "big.fits", [rng.normal(0, 1, shape)], [ccd_header(crpix=(1024.0, 2048.0))])
    wpath = write_mef(tmp_path / "big.weight.fits", [np.ones(shape)], [fits.Header()])

    def resident_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

    if not os.path.exists("/proc/self/statm"):
        pytest.skip("needs /proc to read the resident set")
    before = resident_mb()
    ccds = read_exposure(path, wpath)
    grown = resident_mb() - before
    # the two arrays are 64 MB together; blocks of 256 rows are 2 MB each
    assert grown < 16, f"{grown:.0f} MB resident after reading"
    assert ccds[0].n_bad_pixels == 0


@pytest.mark.parametrize("key", ["MAGZP", "GAIN", "SATURATE"])
def test_missing_keyword(tmp_path, key):
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    with fits.open(image_path, mode="update") as h:
        del h[2].header[key]
    with pytest.raises(ShearfitKeyError) as exc:
        read_exposure(image_path, weight_path)
    msg = one_line(exc)
    assert image_path in msg and "HDU 2 (CCD2)" in msg and key in msg


def test_bad_keyword_value(tmp_path):
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    with fits.open(image_path, mode="update") as h:
        h[1].header["GAIN"] = "high"
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(image_path, weight_path)
    msg = one_line(exc)
    assert image_path in msg and "HDU 1" in msg and "GAIN" in msg


@pytest.mark.parametrize("ctypes, words", [
    (("LINEAR", "LINEAR"), "no celestial WCS"),
    (("RA---XYZ", "DEC--XYZ"), "WCS cannot be read"),
])
def test_bad_wcs(tmp_path, ctypes, words):
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    with fits.open(image_path, mode="update") as h:
        h[1].header["CTYPE1"], h[1].header["CTYPE2"] = ctypes
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(image_path, weight_path)
    msg = one_line(exc)
    assert words in msg and image_path in msg and "HDU 1" in msg


def test_weight_layout_must_match(tmp_path):
    image_path, _, _ = two_ccd_exposure(tmp_path, with_weight=False)
    one = write_mef(tmp_path / "one.weight.fits", [np.ones((80, 60))], [fits.Header()])
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(image_path, one)
    msg = one_line(exc)
    assert image_path in msg and one in msg and "layout" in msg

    small = write_mef(tmp_path / "small.weight.fits", [np.ones((80, 60)), np.ones((80, 59))],
                      [fits.Header(), fits.Header()])
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(image_path, small)
    msg = one_line(exc)
    assert image_path in msg and small in msg and "HDU 2" in msg and "(80, 59)" in msg


@pytest.mark.parametrize("value", [-1.0, np.nan, np.inf])
def test_invalid_weights(tmp_path, value):
    image_path, weight_path, _ = two_ccd_exposure(tmp_path)
    with fits.open(weight_path, mode="update") as h:
        h[2].data[3, 4] = value
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(image_path, weight_path)
    msg = one_line(exc)
    assert weight_path in msg and "HDU 2" in msg and "negative, NaN or infinite" in msg


def test_exposure_file_errors(tmp_path):
    with pytest.raises(ShearfitIOError) as exc:
        read_exposure(tmp_path / "none.fits")
    assert "none.fits" in one_line(exc)
    image_path, _, _ = two_ccd_exposure(tmp_path, with_weight=False)
    with pytest.raises(ShearfitIOError) as exc:
        read_exposure(image_path, tmp_path / "none.weight.fits")
    assert "none.weight.fits" in one_line(exc)
    Table({"a": [1]}).write(tmp_path / "table.fits")
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(tmp_path / "table.fits")
    assert "table.fits" in one_line(exc) and "no image HDU" in str(exc.value)
    fits.PrimaryHDU(np.zeros((10, 10), dtype=np.float32), header=ccd_header()).writeto(tmp_path / "flat.fits")
    with pytest.raises(ShearfitValueError) as exc:
        read_exposure(tmp_path / "flat.fits")
    assert "flat.fits" in one_line(exc) and "no scatter" in str(exc.value)


def test_photometric_scale():
    # A source of magnitude m has 10**(-0.4 (m - magzp)) counts and common flux 10**(-0.4 (m - 30)).
    m, zp = 23.7, 31.2
    counts = 10 ** (-0.4 * (m - zp))
    common = 10 ** (-0.4 * (m - COMMON_ZEROPOINT))
    assert photometric_scale(zp) == pytest.approx(counts / common, rel=1e-12)
    assert photometric_scale(30.0) == 1.0
    np.testing.assert_allclose(photometric_scale(np.array([30.0, 32.5])), [1.0, 10.0])


# --- output -------------------------------------------------------------------------

def test_output_columns_and_empty_rows():
    names = [c.name for c in output_columns()]
    assert names == ["id", "ra", "dec", "mag", "e1", "e2", "weight", "e_var", "fitclass", "snr",
                     "scalelength", "bulge_fraction", "model_flux", "n_exposures_used", "psf_e1", "psf_e2",
                     "psf_fwhm", "m", "star_pvalue", "stamp_size", "flux_snr", "round_scalelength", "iso_weight"]
    row = empty_result_row()
    assert set(row) == set(names) - {"id", "ra", "dec", "mag"}
    assert row["weight"] == 0 and row["fitclass"] == FITCLASS_FIT_FAILED and np.isnan(row["e1"])
    assert row["iso_weight"] == 0 and np.isnan(row["flux_snr"])
    assert empty_result_row(FITCLASS_OFF_EXPOSURES)["fitclass"] == FITCLASS_OFF_EXPOSURES
    cat = Table({"id": ["a", "b"], "ra": [1.0, 2.0], "dec": [3.0, 4.0], "mag": [20.0, 21.0]})
    out = empty_output_table(cat)
    assert out.colnames == names and list(out["id"]) == ["a", "b"]
    assert np.all(out["weight"] == 0) and np.all(out["fitclass"] == FITCLASS_FIT_FAILED)


def small_table():
    return Table({"id": np.arange(3), "e1": [0.1, -0.2, 0.3]})


def test_write_catalog_atomic_round_trip(tmp_path):
    path = tmp_path / "shear.fits"
    cfg = {"stamp_size": 48, "catalog": "/x/" + "y" * 200 + ".fits"}
    cards = provenance_cards(cfg, version="9.9") + [("CALALPHA", 0.057, "calibration alpha"),
                                                     ("LONGKEYWORD", 1.5)]
    write_catalog_atomic(small_table(), path, cards)
    t = Table.read(path)
    assert list(t["id"]) == [0, 1, 2]
    hdr = fits.getheader(path, 1)
    assert json.loads(hdr["SFCONFIG"]) == cfg and hdr["SFVERS"] == "9.9" and hdr["CALALPHA"] == 0.057
    assert hdr["LONGKEYWORD"] == 1.5
    assert os.listdir(tmp_path) == ["shear.fits"]
    write_catalog_atomic(small_table()[:1], path, {"A": (1, "one")})  # replaces an existing file
    assert len(Table.read(path)) == 1 and fits.getheader(path, 1)["A"] == 1


def test_write_catalog_atomic_leaves_nothing_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "shear.fits"
    bad = Table({"id": [1, 2], "obj": np.array([{"a": 1}, None], dtype=object)})  # not representable in FITS
    with pytest.raises(ShearfitValueError) as exc:
        write_catalog_atomic(bad, path)
    assert str(path) in one_line(exc)
    assert os.listdir(tmp_path) == []

    with pytest.raises(ShearfitValueError):
        write_catalog_atomic(small_table(), path, [("NAXIS2", 7)])
    assert os.listdir(tmp_path) == []

    def failing_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(ShearfitIOError) as exc:
        write_catalog_atomic(small_table(), path)
    assert str(path) in one_line(exc) and "No space left" in str(exc.value)
    assert os.listdir(tmp_path) == []


def test_write_catalog_atomic_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "shear.fits"
    write_catalog_atomic(small_table(), path)
    before = path.read_bytes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fits.HDUList, "writeto", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_catalog_atomic(small_table()[:1], path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["shear.fits"]


def test_write_catalog_atomic_bad_directory(tmp_path):
    path = tmp_path / "no" / "such" / "dir" / "shear.fits"
    with pytest.raises(ShearfitIOError) as exc:
        write_catalog_atomic(small_table(), path)
    msg = one_line(exc)
    assert str(path) in msg and "does not exist" in msg


def test_write_catalog_atomic_unwritable_directory(tmp_path, monkeypatch):
    d = tmp_path / "ro"
    d.mkdir()
    # chmod cannot stop root (tests may run as root in containers), so fake what the OS would say.
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if os.fspath(p) == str(d) else real_access(p, mode))
    with pytest.raises(ShearfitIOError) as exc:
        write_catalog_atomic(small_table(), d / "shear.fits")
    msg = one_line(exc)
    assert str(d / "shear.fits") in msg and "not writable" in msg
    monkeypatch.undo()

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "open", denied)
    with pytest.raises(ShearfitIOError) as exc:
        write_catalog_atomic(small_table(), d / "shear.fits")
    msg = one_line(exc)
    assert str(d / "shear.fits") in msg and "Permission denied" in msg
    monkeypatch.undo()
    assert os.listdir(d) == []
