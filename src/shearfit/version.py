"""The installed version of shearfit (the source tree's own when not installed)."""

from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("shearfit")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
