"""Memory per object (issue 30, item 5): the estimate made before a fit, and the limit ``max_object_memory_mb``.

The estimate (:func:`shearfit.pipeline.memory.fit_memory_bytes`) grows with the stamp and the exposures and
bounds the measured peak of a fit from above, within a few times; on a small GalSim field, an object whose
next stamp would need more than the limit gets fitclass -8 and weight 0, the others are measured as before.
"""

import tracemalloc

import numpy as np
import pytest
import yaml
from astropy.table import Table

galsim = pytest.importorskip("galsim")

import shearfit  # noqa: E402
from shearfit.errors import FITCLASS_MEMORY, FITCLASS_TOO_LARGE, ShearfitValueError  # noqa: E402
from shearfit.io.fieldconfig import load_field_config  # noqa: E402
from shearfit.pipeline.driver import measure_field, psf_moments  # noqa: E402
from shearfit.pipeline.memory import fit_memory_bytes  # noqa: E402
from shearfit.simulate.stamps import galaxy_profile, moffat_psf, ring_set  # noqa: E402
from skyfield import DEC0, PIX, RA0, write_dithered_exposure  # noqa: E402

MIB = 2.0 ** 20


def _fwhm(psf):
    """The PSF's FWHM in pixels as the pipeline takes it: 2.3548 times its adaptive-moments sigma."""
    return 2.3548 * psf_moments(psf)[0]


def test_estimate_grows_with_stamp_and_exposures():
    cfg = shearfit.FitConfig()
    sides = [48, 64, 96, 128]
    for n in (1, 7):
        est = [fit_memory_bytes(s, n, cfg, psf_fwhm=4.0) for s in sides]
        assert all(a < b for a, b in zip(est, est[1:]))
    for s in sides:
        est = [fit_memory_bytes(s, n, cfg, psf_fwhm=4.0) for n in (1, 2, 7, 14)]
        assert all(a < b for a, b in zip(est, est[1:]))
    # a sharper PSF keeps more Fourier modes; an unknown one counts them all (the bound for any PSF)
    assert fit_memory_bytes(128, 7, cfg, psf_fwhm=2.0) > fit_memory_bytes(128, 7, cfg, psf_fwhm=4.0)
    assert fit_memory_bytes(128, 7, cfg) >= fit_memory_bytes(128, 7, cfg, psf_fwhm=1.0)
    # metacal's five versions; no alias correction: the stamp's own grid
    assert fit_memory_bytes(64, 7, cfg, psf_fwhm=4.0, metacal=True) == 2 * fit_memory_bytes(64, 7, cfg, psf_fwhm=4.0)
    assert fit_memory_bytes(64, 7, cfg.replace(alias_correction="none")) < fit_memory_bytes(64, 7, cfg)
    # the default limit leaves 7 exposures on 128-pixel stamps alone, even with unknown PSFs
    assert fit_memory_bytes(128, 7, cfg) < 1024 * MIB


def test_estimate_bounds_a_measured_peak():
    """One object on 3 exposures of 48-pixel stamps: the estimate is above the tracemalloc peak of its fit and
    within a few times it, with the compiled loops and with the numpy lines alike (``SHEARFIT_ISA=numpy``; their
    unbinned sums take the models in blocks of ``likelihood.NUMPY_BLOCK_ELEMENTS`` (model, mode) pairs: all at
    once, they held 124 MB against an estimate of 9). A first fit on 32-pixel stamps builds what every worker
    builds once (profile tables, lazy imports), not the 48-pixel alias tables."""
    cfg = shearfit.FitConfig()
    warm = ring_set(1, (0.0, 0.0), np.random.default_rng(1), n_rotations=1, n_exposures=3, stamp_size=32,
                    mag_range=(23.0, 24.5), snr_range=(20, 30), rotate_exposures=True)[0]
    shearfit.measure_object(warm[0], warm[1]["mag"], cfg)
    obs, truth = ring_set(1, (0.0, 0.0), np.random.default_rng(2), n_rotations=1, n_exposures=3, stamp_size=48,
                          snr_range=(20, 40), rotate_exposures=True, jacobian_jitter=0.01)[0]
    est = fit_memory_bytes(48, len(obs), cfg, psf_fwhm=[_fwhm(o.psf) for o in obs])
    tracemalloc.start()
    try:
        res = shearfit.measure_object(obs, truth["mag"], cfg)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert res.fitclass in (0, 1)
    assert peak < est < 6 * peak, (peak / MIB, est / MIB)

@pytest.fixture(scope="module")
def big_and_small(tmp_path_factory):
    """Two exposures (the second rotated by 30 degrees) of a large galaxy (scalelength 1.2": its truncated
    model, 29 pixels, does not fit half a 48-pixel stamp; it does half a 64-pixel one) and a small one
    (0.3"), 120 pixels apart, as test_field_pipeline's large-galaxy field. Returns the config and each
    exposure's PSF FWHM (pixels)."""
    d = tmp_path_factory.mktemp("memory")
    n = 300
    rng = np.random.default_rng(5)
    gals = [(1, -60.0, 1.2, (0.25, -0.15), 1e6, 19.0), (2, 60.0, 0.3, (0.1, 0.2), 4e4, 21.0)]
    radec = [(RA0 - dx * PIX / 3600 / np.cos(np.radians(DEC0)), DEC0) for _, dx, *_ in gals]
    specs, fwhm = [], []
    sources = [(ra, dec, galaxy_profile(r, 0.0, e[0], e[1], flux=flux))
               for (_, _, r, e, flux, _), (ra, dec) in zip(gals, radec)]
    for x, (shift, ang) in enumerate([((0.0, 0.0), 0.0), ((2.3, -1.6), 30.0)]):
        spec, pim = write_dithered_exposure(d, f"e{x}", n, shift, ang, sources, moffat_psf(0.7, 3.0, 0.03, 0.02), rng)
        fwhm.append(_fwhm(pim))
        specs.append(spec)
    Table(rows=[(i, ra, dec, mag) for (i, *_, mag), (ra, dec) in zip(gals, radec)],
          names=("id", "ra", "dec", "mag")).write(d / "objects.fits")
    (d / "field.yaml").write_text(yaml.safe_dump({"exposures": specs, "catalog": "objects.fits"}))
    return d, fwhm


def test_object_over_the_memory_limit_gets_its_fitclass(big_and_small):
    d, fwhm = big_and_small
    cfg = shearfit.FitConfig()
    e48, e64 = (fit_memory_bytes(s, 2, cfg, psf_fwhm=fwhm) for s in (48, 64))
    limit = float(np.sqrt(e48 * e64) / MIB)       # 48-pixel stamps pass, 64-pixel ones do not
    t = measure_field(load_field_config(d / "field.yaml", [f"max_object_memory_mb={limit!r}"]), d / "limited.fits")
    big, small = t[0], t[1]
    # the large galaxy was too large for 48 pixels (-4), and its 64-pixel fit would need more than the limit
    assert big["fitclass"] == FITCLASS_MEMORY and big["weight"] == 0 and big["stamp_size"] == 64
    assert small["fitclass"] == 0 and small["weight"] > 0 and small["stamp_size"] == 48
    assert small["n_exposures_used"] == 2 and abs(small["e1"] - 0.1) < 0.05 and abs(small["e2"] - 0.2) < 0.05
    # the paper's fixed stamp: the limit is never reached, the large galaxy is too large for its stamp
    t = measure_field(load_field_config(d / "field.yaml", [f"max_object_memory_mb={limit!r}", "max_stamp_size=48"]),
                      d / "fixed.fits")
    assert t[0]["fitclass"] == FITCLASS_TOO_LARGE and t[1]["fitclass"] == 0
    # a limit below every stamp: nothing is fitted, every object -8 on its first stamp, the run completes
    t = measure_field(load_field_config(d / "field.yaml", ["max_object_memory_mb=0.5"]), d / "none.fits")
    assert list(t["fitclass"]) == [FITCLASS_MEMORY] * 2 and list(t["stamp_size"]) == [48, 48]
    assert np.all(t["weight"] == 0) and np.all(t["n_exposures_used"] == 0)


@pytest.mark.parametrize("value, message", [("-1", "must be a number of MiB, positive, or 0 for no limit"),
                                            (".nan", "must be a number of MiB"),
                                            ("lots", "must be of type float")])
def test_bad_memory_limit_is_an_error_naming_the_key(big_and_small, value, message):
    d, _ = big_and_small
    with pytest.raises(ShearfitValueError, match="max_object_memory_mb") as err:
        load_field_config(d / "field.yaml", [f"max_object_memory_mb={value}"])
    assert message in str(err.value) and "field.yaml" in str(err.value)


def test_zero_means_no_limit(big_and_small):
    d, _ = big_and_small
    cfg = load_field_config(d / "field.yaml", ["max_object_memory_mb=0"])
    assert cfg.pipeline.max_object_memory_mb == 0.0
    assert load_field_config(d / "field.yaml").pipeline.max_object_memory_mb == 1024.0
