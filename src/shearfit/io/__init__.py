"""Reading and writing a field: FITS exposures, weights and catalogues, WCS, postage stamps, given PSF models
(FITS images, PSFEx) and the field's YAML config; the shear catalogue's FITS output.

- :mod:`.fieldconfig`: the field YAML (the public contract) and the pipeline's settings
- :mod:`.fits`: exposures, weights, catalogues, the output catalogue and its provenance header
- :mod:`.wcs`: local Jacobians of a celestial WCS, pixel and sky positions
- :mod:`.stamps`: postage stamps with their masks
- :mod:`.psfinput`: given PSF models (FITS images, PSFEx ``.psf`` files)
"""
