"""Simulations with GalSim as the independent reference renderer.

:mod:`.stamps` makes postage stamps of the paper's galaxy population on
several dithered exposures, wrapped as :class:`shearfit.Observation` objects,
and ring sets for shear-bias tests; :mod:`.shear_bias` turns measured ring
sets into the multiplicative and additive shear bias with bootstrap errors.
"""

from .stamps import (  # noqa: F401
    ZERO_POINT,
    draw_psf_image,
    draw_stamp,
    galaxy_profile,
    jacobian_wcs,
    kolmogorov_psf,
    mag_to_flux,
    make_observations,
    moffat_psf,
    noise_for_snr,
    ring_set,
)

__all__ = ["ZERO_POINT", "draw_psf_image", "draw_stamp", "galaxy_profile", "jacobian_wcs", "kolmogorov_psf",
           "mag_to_flux", "make_observations", "moffat_psf", "noise_for_snr", "ring_set"]
