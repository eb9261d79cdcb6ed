"""shearfit systematics: PSF-galaxy cross-correlation, weights and weight bias on catalogues with known answers."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from shearfit.app.cli import main
from shearfit.errors import ShearfitIOError
from shearfit.stats.systematics import psf_galaxy_xcorr, read_catalogs, weight_bias


def _catalog(n=20000, seed=0, leak=0.1, weight_bias_amp=0.0):
    """Galaxies whose estimates leak ``leak`` x e_psf below SNR 20 (none above); weights optionally favouring
    galaxies aligned with the PSF."""
    rng = np.random.default_rng(seed)
    snr = np.exp(rng.uniform(np.log(5), np.log(200), n))
    r = rng.uniform(0.1, 1.0, n)
    ep = rng.normal(0, 0.05, (2, n))
    ei = rng.normal(0, 0.25, (2, n))
    noise = rng.normal(0, 1, (2, n)) * (2.0 / snr)
    alpha = np.where(snr < 20, leak, 0.0)
    e = ei + noise + alpha * ep
    w = 1.0 / (0.25 ** 2 + (2.0 / snr) ** 2) * (1 + weight_bias_amp * (ei[0] * ep[0] + ei[1] * ep[1]) / 0.0125)
    t = Table({"id": np.arange(n), "ra": rng.uniform(0, 1, n), "dec": rng.uniform(0, 1, n), "e1": e[0], "e2": e[1],
               "psf_e1": ep[0], "psf_e2": ep[1], "weight": np.clip(w, 0, None), "fitclass": np.zeros(n, int),
               "snr": snr, "scalelength": r, "mag": 24 - 2.5 * np.log10(snr / 10)})
    truth = Table({"id": np.arange(n), "e1_int": ei[0], "e2_int": ei[1], "is_star": np.zeros(n, bool)})
    return t, truth, alpha


def test_psf_galaxy_xcorr_finds_the_injected_leakage():
    t, _, _ = _catalog(n=40000, leak=0.3)
    edges = np.array([5, 10, 20, 50, 200.0001])
    x = psf_galaxy_xcorr(t, "snr", edges, rng=np.random.default_rng(1))
    expect = 0.3 * 2 * 0.05 ** 2     # alpha <|e_psf|^2>
    low, high = x[:2], x[2:]
    assert np.all(np.abs(low["xi_psf_gal"] - expect) < 4 * low["xi_err"])
    assert np.all(np.abs(high["xi_psf_gal"]) < 4 * high["xi_err"])
    assert np.all(low["xi_psf_gal"] > 3 * low["xi_err"])


def test_subsample_errors_match_the_scatter_between_catalogues():
    vals, errs = [], []
    for seed in range(12):
        t, _, _ = _catalog(n=4000, seed=seed, leak=0.0)
        x = psf_galaxy_xcorr(t, "snr", np.array([5.0, 200.0001]), rng=np.random.default_rng(seed))
        vals.append(x["xi_psf_gal"][0])
        errs.append(x["xi_err"][0])
    ratio = np.std(vals) / np.mean(errs)
    assert 0.5 < ratio < 2.0


def test_weight_bias_is_detected():
    t, truth, _ = _catalog(weight_bias_amp=0.5)
    t["e1_int"], t["e2_int"] = truth["e1_int"], truth["e2_int"]
    wb = weight_bias(t, rng=np.random.default_rng(0))
    assert len(set(wb["group"])) == 4
    for g in set(wb["group"]):
        s = wb[wb["group"] == g]
        slope = np.polyfit(s["e_psf"], s["w_e_int"], 1)[0]
        assert slope > 0.3   # weights favour galaxies aligned with the PSF
    t2, truth2, _ = _catalog(weight_bias_amp=0.0)
    t2["e1_int"], t2["e2_int"] = truth2["e1_int"], truth2["e2_int"]
    wb2 = weight_bias(t2, rng=np.random.default_rng(0))
    pull = wb2["w_e_int"] / wb2["err"]
    assert np.sqrt(np.mean(pull ** 2)) < 2.0


def test_cli_tables_plots_and_errors(tmp_path, capsys):
    t, truth, _ = _catalog(n=6000)
    # each field's catalogue carries its own configuration in the header, as shearfit measure writes it
    for name, part, cfg in (("f1.fits", t[:3000], "field one"), ("f2.fits", t[3000:], "field two")):
        part = part.copy()
        part.meta["SFCONFIG"] = cfg
        part.write(tmp_path / name)
    truth.write(tmp_path / "truth.fits")
    out = tmp_path / "sys"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")       # no metadata-merge warning per field
        assert main(["systematics", str(tmp_path / "f1.fits"), str(tmp_path / "f2.fits"), "--truth",
                     str(tmp_path / "truth.fits"), "--out", str(out), "--n-bins", "5"]) == 0
    assert "PSF-galaxy" in capsys.readouterr().out
    for name in ("psf_galaxy.png", "weights.png", "weight_bias.png", "systematics.fits"):
        assert (out / name).stat().st_size > 0
    with fits.open(out / "systematics.fits") as h:
        fields = set(h["PSFGAL_SNR"].data["field"])
        assert "all" in fields and len(fields) == 3
        assert len(h["WEIGHTBIAS"].data) == 24
        assert h[0].header["NGAL"] == 6000
    bad = t.copy()
    bad.remove_column("psf_e1")
    bad.write(tmp_path / "bad.fits")
    with pytest.raises(ShearfitIOError, match="psf_e1"):
        read_catalogs([tmp_path / "bad.fits"])
    assert main(["systematics", str(tmp_path / "bad.fits"), "--out", str(tmp_path / "sys2")]) != 0
