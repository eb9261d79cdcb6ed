"""shearfit: Bayesian bulge+disk shear measurement on individual exposures (lensfit)."""

from .version import __version__
from .config import FitConfig, fit_config_from_mapping  # noqa: E402
from .errors import ShearfitError, ShearfitValueError, ShearfitKeyError, ShearfitIOError  # noqa: E402
from .observation import Observation, FitResult  # noqa: E402

__all__ = ["__version__", "FitConfig", "fit_config_from_mapping", "Observation", "FitResult",
           "ShearfitError", "ShearfitValueError", "ShearfitKeyError", "ShearfitIOError"]
from .engine.measure import measure_object, measure_objects  # noqa: E402
from .engine.model import psf_moffat, render_object  # noqa: E402

__all__ += ["measure_object", "measure_objects", "render_object", "psf_moffat"]
