"""The package's exception hierarchy.

Every exception raised for bad input subclasses both :class:`ShearfitError`
and the matching built-in, so ``except ValueError`` still works, and every
one pickles (it carries only its message), so it crosses process boundaries.
"""


class ShearfitError(Exception):
    """Base class of every error shearfit raises on purpose."""


class ShearfitValueError(ShearfitError, ValueError):
    """A value (argument, config setting, array, header keyword) is not allowed."""


class ShearfitKeyError(ShearfitError, KeyError):
    """A required key, column or keyword is missing, or an unknown one was given."""

    def __str__(self):  # KeyError quotes its message; a one-line error should not
        return str(self.args[0]) if self.args else ""


class ShearfitIOError(ShearfitError, OSError):
    """A file cannot be read or written."""


# Catalogue codes of the ``fitclass`` column (see docs/interface.rst).
FITCLASS_GALAXY = 0
FITCLASS_STAR = 1
FITCLASS_FEW_EXPOSURES = -1
FITCLASS_FIT_FAILED = -2
FITCLASS_BLENDED = -3
FITCLASS_TOO_LARGE = -4
FITCLASS_CENTROID = -5
FITCLASS_OFF_EXPOSURES = -6
FITCLASS_BAD_INPUT = -7
FITCLASS_MEMORY = -8

FITCLASS_NAMES = {
    FITCLASS_GALAXY: "galaxy",
    FITCLASS_STAR: "star",
    FITCLASS_FEW_EXPOSURES: "too few usable exposures",
    FITCLASS_FIT_FAILED: "fit failed",
    FITCLASS_BLENDED: "blended or complex",
    FITCLASS_TOO_LARGE: "too large for the stamp",
    FITCLASS_CENTROID: "centroid too far from the input position",
    FITCLASS_OFF_EXPOSURES: "off every exposure",
    FITCLASS_BAD_INPUT: "bad catalogue row (ra, dec or mag not finite, or dec outside [-90, 90])",
    FITCLASS_MEMORY: "its fit would need more memory than max_object_memory_mb",
}
