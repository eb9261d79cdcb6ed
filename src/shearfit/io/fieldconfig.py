"""The YAML config of a field: which files to read, and every setting of the run.

A field config (docs/interface.rst, "Input: a field") names the exposures, the
object catalogue, optionally the PSF stars and the output, all relative to
the config file; any other top-level key is a setting, either of the
per-object engine (:class:`shearfit.config.FitConfig`) or of the field
pipeline (:class:`PipelineConfig`, below). An unknown key, a value of the
wrong type or a missing required key is an error that names the key and the
file, as in TreeCorr's and Piff's configs.

Settings may be overridden on the command line with ``key=value`` strings,
GalSim- and Piff-style (``shearfit measure field.yaml stamp_size=64``); the
value is parsed as YAML (never evaluated as Python). A dotted key reaches into
the exposure list: ``exposures.0.psf=exp0.psf.fits``.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
from dataclasses import dataclass, field, fields
from typing import Any, Mapping, Optional, Sequence


from ..config import FitConfig, check_choices, coerce_setting, fit_config_from_mapping, setting
from ..files import load_yaml
from ..errors import ShearfitError, ShearfitIOError, ShearfitKeyError, ShearfitValueError

__all__ = [
    "ExposureSpec",
    "PipelineConfig",
    "FieldConfig",
    "load_field_config",
    "field_config_from_mapping",
    "parse_overrides",
    "describe_pipeline",
]


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the field pipeline (stamps, masking, exposure selection).

    These are what the paper fixes for the step between the images and the
    per-object fit (sec. 3.6); the fit itself is set by
    :class:`shearfit.config.FitConfig`. Each field's ``metadata`` holds its
    help text and paper reference (see :func:`describe_pipeline`).
    """

    stamp_size: int = setting(
        48, "side of the square postage stamp cut around each object on each exposure, pixels",
        "sec. 3.6 (48 pixels, about 9 arcsec)")
    max_stamp_size: int = setting(
        128, "an object whose truncated model is too large for its stamp is cut and measured again on larger "
        "stamps (64, 96, 128, 192, 256 pixels) up to this side; fitclass -4 only beyond it (stamp_size: the "
        "paper's fixed stamp)", "sec. 3.6 (implementation)")
    max_object_memory_mb: float = setting(
        1024.0, "largest memory, MiB, one object's fit may need on one stamp size, estimated before the fit "
        "from the stamp side, the exposures and their PSFs' FWHM (shearfit.pipeline.memory; an upper bound: "
        "15 MiB for 7 exposures on 48-pixel stamps, 90 on 128-pixel ones, with 0.7-arcsec PSFs): an object "
        "that would need more is not measured on that size (fitclass -8, weight 0) and the run goes on; "
        "0: no limit", "implementation")
    isophote_nsigma: float = setting(
        2.0, "isophote level, in units of the smoothed pixel noise, that defines an object's extent for "
        "neighbour masking, blend detection and the centroid test", "sec. 3.6 (two-sigma isophote)")
    isophote_centroid_max_shift: float = setting(
        4.0, "largest distance, pixels, of the intensity-weighted centroid inside the isophote from the "
        "catalogue position (fitclass -5 beyond); the fitted centre has its own limit, max_centroid_shift",
        "sec. 3.6")
    min_exposures: int = setting(
        1, "fewest usable exposures an object needs to be fitted (fitclass -1 below)",
        "DESIGN: the paper fits whatever n >= 1 exposures are usable, sec. 3.6")
    neighbour_mask: bool = setting(
        True, "mask neighbours whose isophotes do not touch the target's (set to the background, weight 0) "
        "instead of flagging the target as blended", "sec. 3.6")
    deblend_min_pixels: int = setting(
        8, "regions of the smoothed isophote map with fewer pixels are merged into a touching neighbour "
        "before an object is called complex", "sec. 3.6, footnote")
    catalogue_blends: bool = setting(
        True, "also flag an object blended (fitclass -3) when the position of another input-catalogue object "
        "on its first stamp (stamp_size) lies inside its isophote: a pair closer than the PSF, which the "
        "deblender sees as one maximum, is otherwise fitted as one galaxy (false: the deblender's maxima "
        "alone, as in the paper)",
        "sec. 3.6 (the input catalogue's blends); implementation")
    drop_masked_exposures: bool = setting(
        True, "leave out an exposure whose masked pixels (weight 0) fall inside the target's isophote; "
        "masked pixels outside it only get zero weight", "sec. 3.6")

    chunk_size: int = setting(
        256, "objects per checkpoint chunk: finished chunks are kept in OUTPUT.parts/ (each written "
        "atomically), so that rerunning the same command after an interruption resumes where it stopped",
        "implementation")

    metacal_delta: float = setting(
        0.01, "with calibration: metacal, the shear applied to the deconvolved stamps in each component",
        "Huff & Mandelbaum 2017; Sheldon & Huff 2017")
    metacal_seed: int = setting(
        0, "seed of the noise fields shearfit adds: metacal's symmetrising ones (calibration: metacal) and "
        "those of the engine's noise_bias_correction (one stream per object id and use)",
        "implementation")
    metacal_noise_sign: int = setting(
        1, "with calibration: metacal, 1, or -1 to negate the symmetrising noise fields: a simulated field's "
        "antithetic twin (the same field with its pixel noise negated) measured with -1 and the field measured "
        "with 1 cancel the terms odd in either noise (benchmarks/field_test.py --antithetic)",
        "implementation", (1, -1))

    metacal_psf: str = setting(
        "dilated", "with calibration: metacal, the versions' new PSF: 'dilated' (the exposure's PSF dilated by "
        "1 + 2 metacal_delta) or 'round' (the round envelope below it, a function of |k| alone: no PSF anisotropy "
        "reaches the ellipticities, at the price of noisier responses for the smallest galaxies)", "Sheldon & Huff 2017",
        ("dilated", "round"))
    metacal_replay: bool = setting(
        True, "with calibration: metacal, the sheared versions replay the noshear fit's choices (Fourier modes, "
        "position, size nodes, ellipticity samples): their estimates follow the pixels smoothly and the four cost "
        "about 1.2 plain fits together. false: each version is fitted on its own, so that R also holds the "
        "estimator's response through its choices, which the replays leave out (on galaxies outside the model "
        "family m higher by +0.011 +- 0.007 at SNR 10-14, of the replays' -0.028 there, and by +0.0024 +- "
        "0.0016 at 14-20: benchmarks/README.md, sessions 44-48), for 1.5-1.8 times the time of the fits and a "
        "noisier response without noise", "implementation")
    metacal_own_grid: bool = setting(
        False, "with calibration: metacal and metacal_replay, each sheared version runs the adaptive ellipticity "
        "grid on its own likelihood (the noshear fit's samples evaluated for the four together) instead of replaying "
        "the noshear fit's samples and cells, so that R also holds the estimate's response through its grid (on "
        "galaxies outside the model family m higher by +0.009 +- 0.004 at SNR 10-14, about half of what "
        "metacal_replay: false takes, for 3.07 instead of 2.78 plain fits: benchmarks/README.md, session 46)",
        "implementation")
    metacal_own_position: bool = setting(
        False, "with calibration: metacal and metacal_replay, each sheared version finds its own position (the "
        "fit's Newton search on its own cross-correlation, from the noshear fit's peak) instead of replaying the "
        "noshear fit's; with metacal_own_grid as well, m is that of versions fitted on their own to -0.007 +- 0.005 "
        "at SNR 10-14 and +0.0001 +- 0.0017 at 14-20, for 3.26 plain fits (benchmarks/README.md, session 46)",
        "implementation")

    psf_size: int = setting(25, "side of the fitted PSF model and of the star stamps, native pixels (odd)", "sec. 5")
    psf_oversampling: int = setting(
        1, "PSF model samples per pixel: 1 is the paper's native model (sinc-centred stars); 3 reconstructs "
        "the PSF above Nyquist from stars at many sub-pixel phases", "sec. 5, App. A (the next step named there)")
    psf_order: int = setting(3, "polynomial order of each PSF pixel over the field of view", "sec. 5")
    psf_alias_order: int = setting(0, "polynomial order over the field of the above-Nyquist PSF components "
                                   "(psf_oversampling > 1)", "implementation")
    psf_min_stars: int = setting(40, "CCDs with fewer usable stars are left out of an exposure's PSF model "
                                  "(and of the measurement)", "sec. 5")
    psf_min_snr: float = setting(20.0, "smallest integrated SNR (8-pixel aperture) of a PSF star", "sec. 5")
    psf_saturation_fraction: float = setting(0.5, "a star whose central pixel exceeds this fraction of SATURATE "
                                               "is not used", "sec. 5")
    psf_isolation_radius: float = setting(8.0, "no other catalogue object may lie this close to a PSF star, "
                                            "pixels", "sec. 5")
    psf_iterations: int = setting(2, "rounds of star centring (cross-correlation with the model) and refitting "
                                  "(a third moves the models by about 1e-4 of their peak)", "sec. 5")
    psf_native_width: float = setting(
        1.0, "relative width of the prior on the native PSF model's transform: frequencies where the PSF is below "
        "the stars' noise follow a Moffat fitted to the model instead of the noise (0: plain least squares at every "
        "frequency, the paper's fit)", "implementation")
    psf_clip: float = setting(0.0, "drop stars whose reduced chi^2 exceeds the median by this many robust "
                                "sigmas before the last fit (0: keep all)", "implementation")
    registration_order: int = setting(1, "polynomial order per CCD of the astrometric registration offsets "
                                      "measured on the PSF stars", "sec. 4")
    psf_moment_grid: int = setting(
        7, "a PSF that varies over a CCD (fitted, PSFEx or Piff model) has its adaptive moments (the catalogue's "
        "psf_e1, psf_e2, psf_fwhm) measured on this many points per axis of each CCD and interpolated to the objects "
        "by a bicubic spline, instead of at every object (0: at every object). 7 leaves them within 5e-6 of the "
        "direct measurement (benchmarks/pipeline_profile.py --compare-with a run with 0)", "implementation")
    psf_bootstrap: int = setting(64, "bootstrap resamplings of the stars for the PSF model's rms "
                                  "(shearfit psf diagnostics)", "sec. 5")

    def __post_init__(self):
        check_choices(self)
        if self.psf_size < 5 or self.psf_size % 2 == 0:
            raise ShearfitValueError(f"setting psf_size={self.psf_size!r} must be an odd number of at least 5")
        if self.psf_oversampling < 1 or self.psf_oversampling % 2 == 0:
            raise ShearfitValueError(f"setting psf_oversampling={self.psf_oversampling!r} must be 1 or odd")
        if self.stamp_size < 8:
            raise ShearfitValueError(f"setting stamp_size={self.stamp_size!r} must be at least 8 pixels")
        if self.max_stamp_size < self.stamp_size:
            raise ShearfitValueError(f"setting max_stamp_size={self.max_stamp_size!r} must be at least stamp_size "
                                     f"({self.stamp_size})")
        for name in ("isophote_nsigma", "isophote_centroid_max_shift"):
            if not getattr(self, name) > 0:
                raise ShearfitValueError(f"setting {name}={getattr(self, name)!r} must be positive")
        if self.min_exposures < 1:
            raise ShearfitValueError(f"setting min_exposures={self.min_exposures!r} must be at least 1")
        if self.deblend_min_pixels < 1:
            raise ShearfitValueError(f"setting deblend_min_pixels={self.deblend_min_pixels!r} must be at least 1")
        if not self.max_object_memory_mb >= 0:
            raise ShearfitValueError(f"setting max_object_memory_mb={self.max_object_memory_mb!r} must be a number "
                                     f"of MiB, positive, or 0 for no limit")
        if self.chunk_size < 1:
            raise ShearfitValueError(f"setting chunk_size={self.chunk_size!r} must be at least 1")
        if self.psf_moment_grid != 0 and self.psf_moment_grid < 4:
            raise ShearfitValueError(f"setting psf_moment_grid={self.psf_moment_grid!r} must be 0 (every object) or at "
                                     f"least 4 (a bicubic spline's points per axis)")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ExposureSpec:
    """The files of one exposure: image, and optionally weight and a given PSF (absolute paths)."""

    image: str
    weight: Optional[str] = None
    psf: Optional[str] = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class FieldConfig:
    """A field's files and every setting of its run, as read from a YAML config.

    Attributes
    ----------
    exposures : tuple of ExposureSpec
        One per exposure, in the config's order, paths absolute.
    catalog : str
        The object catalogue.
    stars : str or None
        PSF stars; None means select them automatically.
    output : str or None
        Default output catalogue (the command line's ``--out`` wins).
    calibration : str or None
        A calibration.yaml from ``shearfit calibrate``: its (alpha, beta) fill
        the ``m`` column; None or ``simulations`` uses shearfit's default
        calibration (:data:`shearfit.calib.calibrate.DEFAULT_CALIBRATION`, a
        table of bins fitted on its own simulations); ``metacal`` measures each object's shear response from its own
        images instead (:mod:`shearfit.calib.metacal`; ``m`` is then 0 and the
        catalogue carries the sheared measurements and ``R11`` .. ``R22``).
    fit : FitConfig
        The per-object engine's settings.
    pipeline : PipelineConfig
        The field pipeline's settings.
    source : str
        The config file this came from (or a description), for messages.
    """

    exposures: tuple
    catalog: str
    stars: Optional[str] = None
    output: Optional[str] = None
    calibration: Optional[str] = None
    fit: FitConfig = field(default_factory=FitConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    source: str = "<mapping>"

    def to_dict(self) -> dict:
        """The resolved config as one flat mapping, for provenance.

        It is what a YAML config would hold (paths absolute), so
        :func:`field_config_from_mapping` reads it back to an equal config.
        """
        out = {
            "exposures": [e.to_dict() for e in self.exposures],
            "catalog": self.catalog,
            "stars": self.stars,
            "output": self.output,
            "calibration": self.calibration,
        }
        out.update(self.pipeline.to_dict())
        out.update(self.fit.to_dict())
        return out

    def check_files(self) -> None:
        """Raise :class:`ShearfitIOError` naming the first input file that does not exist."""
        inputs = [("catalog", self.catalog), ("stars", self.stars)]
        if self.calibration not in CALIBRATION_MODES:
            inputs.append(("calibration", self.calibration))
        for i, e in enumerate(self.exposures):
            inputs += [(f"exposures[{i}].image", e.image), (f"exposures[{i}].weight", e.weight),
                       (f"exposures[{i}].psf", e.psf)]
        for key, path in inputs:
            if path is not None and not os.path.isfile(path):
                raise ShearfitIOError(f"{self.source}: {key}: no such file {path}")


# --- schema -----------------------------------------------------------------------------

_FILE_KEYS = ("exposures", "catalog", "stars", "output", "calibration")
_EXPOSURE_KEYS = ("image", "weight", "psf")
_FIT_FIELDS = {f.name: f for f in fields(FitConfig)}
_PIPELINE_FIELDS = {f.name: f for f in fields(PipelineConfig)}
# A setting must mean one thing: a clash would make one key silently set two components.
_CLASH = (set(_FIT_FIELDS) & set(_PIPELINE_FIELDS)) | (set(_FILE_KEYS) & (set(_FIT_FIELDS) | set(_PIPELINE_FIELDS)))
if _CLASH:
    raise RuntimeError(f"settings defined twice (FitConfig and PipelineConfig or file keys): {sorted(_CLASH)}")


def _valid_keys() -> list:
    return list(_FILE_KEYS) + sorted(_PIPELINE_FIELDS) + sorted(_FIT_FIELDS)


def _unknown_hint(key, valid) -> str:
    """'did you mean ...' for a likely typo, else the list of valid keys."""
    close = difflib.get_close_matches(str(key), list(valid), n=1)
    if close:
        return f"did you mean {close[0]!r}?"
    return f"valid: {', '.join(valid)}"


def _resolve(path_value, key: str, base_dir: str, source: str, required: bool) -> Optional[str]:
    if path_value is None:
        if required:
            raise ShearfitKeyError(f"{source}: missing required key {key!r}")
        return None
    if not isinstance(path_value, (str, os.PathLike)) or str(path_value) == "":
        raise ShearfitValueError(f"{source}: {key}={path_value!r} must be a file path (a string)")
    p = os.path.expanduser(os.fspath(path_value))
    return os.path.normpath(os.path.join(base_dir, p))


#: Values of ``calibration:`` that name a method rather than a calibration file.
CALIBRATION_MODES = (None, "simulations", "metacal")


def _calibration_value(value, base_dir, source):
    if isinstance(value, str) and value.strip().lower() in CALIBRATION_MODES:
        return value.strip().lower()
    return _resolve(value, "calibration", base_dir, source, False)


def field_config_from_mapping(mapping: Mapping[str, Any], base_dir: str = ".",
                              source: str = "<mapping>") -> FieldConfig:
    """Build a :class:`FieldConfig` from a parsed config.

    Parameters
    ----------
    mapping : mapping
        The config's top level, as YAML gives it.
    base_dir : str
        Directory that relative paths are relative to (the config file's).
    source : str
        Name of the config in error messages (the file's path).

    Raises
    ------
    ShearfitKeyError
        An unknown key, or a missing required one (``exposures``, an
        exposure's ``image``, ``catalog``).
    ShearfitValueError
        A value of the wrong type or out of its range.
    """
    if not isinstance(mapping, Mapping):
        raise ShearfitValueError(f"{source}: the config must be a mapping of keys to values, "
                                 f"got {type(mapping).__name__}")
    base_dir = os.path.abspath(os.path.expanduser(os.fspath(base_dir)))
    unknown = [k for k in mapping if k not in _FILE_KEYS and k not in _FIT_FIELDS and k not in _PIPELINE_FIELDS]
    if unknown:
        raise ShearfitKeyError(f"{source}: unknown key {unknown[0]!r} ({_unknown_hint(unknown[0], _valid_keys())})")

    raw_exposures = mapping.get("exposures")
    if raw_exposures is None:
        raise ShearfitKeyError(f"{source}: missing required key 'exposures'")
    if not isinstance(raw_exposures, Sequence) or isinstance(raw_exposures, (str, bytes)) or not raw_exposures:
        raise ShearfitValueError(f"{source}: exposures must be a non-empty list of mappings with an 'image' key")
    exposures = []
    for i, item in enumerate(raw_exposures):
        if not isinstance(item, Mapping):
            raise ShearfitValueError(f"{source}: exposures[{i}] must be a mapping with an 'image' key, "
                                     f"got {item!r}")
        bad = [k for k in item if k not in _EXPOSURE_KEYS]
        if bad:
            raise ShearfitKeyError(f"{source}: unknown key {bad[0]!r} in exposures[{i}] "
                                   f"({_unknown_hint(bad[0], _EXPOSURE_KEYS)})")
        exposures.append(ExposureSpec(
            image=_resolve(item.get("image"), f"exposures[{i}].image", base_dir, source, True),
            weight=_resolve(item.get("weight"), f"exposures[{i}].weight", base_dir, source, False),
            psf=_resolve(item.get("psf"), f"exposures[{i}].psf", base_dir, source, False),
        ))

    pipe_kwargs = {k: coerce_setting(k, _PIPELINE_FIELDS[k].type, v, source)
                   for k, v in mapping.items() if k in _PIPELINE_FIELDS}
    fit_map = {k: v for k, v in mapping.items() if k in _FIT_FIELDS}
    try:
        pipeline = PipelineConfig(**pipe_kwargs)
        # FitConfig checks its own types and ranges; its messages name the key, we add the file.
        fit = fit_config_from_mapping(fit_map)
    except ShearfitError as exc:
        if str(exc).startswith(f"{source}:"):
            raise
        raise type(exc)(f"{source}: {exc}") from None

    return FieldConfig(
        exposures=tuple(exposures),
        catalog=_resolve(mapping.get("catalog"), "catalog", base_dir, source, True),
        stars=_resolve(mapping.get("stars"), "stars", base_dir, source, False),
        output=_resolve(mapping.get("output"), "output", base_dir, source, False),
        calibration=_calibration_value(mapping.get("calibration"), base_dir, source),
        fit=fit,
        pipeline=pipeline,
        source=source,
    )


# --- overrides ----------------------------------------------------------------------

def _absolute_paths(value, top_key: str):
    """Make the relative paths of an override absolute against the current directory.

    A path typed on the command line means what the shell means by it,
    not something relative to the config file.
    """
    if top_key not in _FILE_KEYS:
        return value
    if top_key == "calibration" and isinstance(value, str) and value.strip().lower() in CALIBRATION_MODES:
        return value
    if isinstance(value, str) and value:
        return os.path.abspath(os.path.expanduser(value))
    if isinstance(value, Mapping):
        return {k: (_absolute_paths(v, top_key) if k in _EXPOSURE_KEYS else v) for k, v in value.items()}
    if isinstance(value, list):
        return [_absolute_paths(v, top_key) for v in value]
    return value


def parse_overrides(mapping: Mapping[str, Any], overrides: Sequence[str] | None) -> dict:
    """Apply ``key=value`` overrides to a parsed config, returning a new mapping.

    Parameters
    ----------
    mapping : mapping
        The config as read from YAML.
    overrides : sequence of str
        Each ``key=value``; ``key`` is a top-level setting or
        ``exposures.N.image|weight|psf``; ``value`` is parsed as YAML
        (``stamp_size=64`` is an int, ``neighbour_mask=false`` a bool,
        ``stars=`` unsets). Relative paths are relative to the current
        directory.
    """
    if isinstance(overrides, str):  # one override given bare, not in a list
        overrides = [overrides]
    out = dict(mapping)
    if "exposures" in out and isinstance(out["exposures"], list):
        out["exposures"] = [dict(e) if isinstance(e, Mapping) else e for e in out["exposures"]]
    for item in overrides or ():
        if not isinstance(item, str) or "=" not in item:
            raise ShearfitValueError(f"override {item!r} is not of the form key=value")
        key, text = item.split("=", 1)
        key = key.strip()
        value = load_yaml(text, f"override {item!r}") if text.strip() else None
        parts = key.split(".")
        top = parts[0]
        if top not in _FILE_KEYS and top not in _FIT_FIELDS and top not in _PIPELINE_FIELDS:
            raise ShearfitKeyError(f"override {item!r}: unknown key {top!r} ({_unknown_hint(top, _valid_keys())})")
        value = _absolute_paths(value, top)
        if len(parts) == 1:
            out[top] = value
            continue
        exps = out.get("exposures")
        if top != "exposures" or len(parts) != 3 or not parts[1].isdigit() or not isinstance(exps, list):
            raise ShearfitKeyError(f"override {item!r}: {key!r} is not a setting; only exposures.N.KEY "
                                   f"reaches inside the config")
        index, sub = int(parts[1]), parts[2]
        if index >= len(exps) or not isinstance(exps[index], dict):
            raise ShearfitKeyError(f"override {item!r}: there is no exposure {index} "
                                   f"(the config has {len(exps)})")
        if sub not in _EXPOSURE_KEYS:
            raise ShearfitKeyError(f"override {item!r}: unknown key {sub!r} in an exposure "
                                   f"({_unknown_hint(sub, _EXPOSURE_KEYS)})")
        exps[index][sub] = value
    return out


def load_field_config(path, overrides: Sequence[str] | None = None) -> FieldConfig:
    """Read a field's YAML config.

    Parameters
    ----------
    path : str or os.PathLike
        The config file. Paths inside it are relative to its directory.
    overrides : sequence of str, optional
        ``key=value`` settings that replace the file's (see
        :func:`parse_overrides`).

    Returns
    -------
    FieldConfig

    Raises
    ------
    ShearfitIOError
        The file cannot be read.
    ShearfitKeyError, ShearfitValueError
        An unknown, missing or ill-typed key; the message names it and the file.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise ShearfitIOError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ShearfitIOError(f"{path}: cannot read the config: {exc}") from None
    mapping = load_yaml(text, path)
    if mapping is None:
        raise ShearfitValueError(f"{path}: the config is empty; it needs at least 'exposures' and 'catalog'")
    if not isinstance(mapping, Mapping):
        raise ShearfitValueError(f"{path}: the config must be a mapping of keys to values, "
                                 f"got {type(mapping).__name__}")
    mapping = parse_overrides(mapping, overrides)
    return field_config_from_mapping(mapping, base_dir=os.path.dirname(os.path.abspath(path)), source=path)


def describe_pipeline() -> str:
    """One line per pipeline setting: name, default, reference, help."""
    return "\n".join(f"{f.name} = {f.default!r}  [{f.metadata.get('ref', '')}]  {f.metadata.get('help', '')}"
                     for f in fields(PipelineConfig))
