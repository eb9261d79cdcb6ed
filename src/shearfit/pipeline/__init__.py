"""The field pipeline: PSF models, stamps, neighbour masking and blend flags, the joint fits, the catalogue.

- :mod:`.driver`: :func:`~shearfit.pipeline.driver.measure_field` (``shearfit measure``), chunked,
  resumable, on worker processes or a Dask cluster
- :mod:`.blends`: segmentation of a stamp, neighbour masks, blend and complexity flags (sec. 3.6)
- :mod:`.memory`: the memory of one object's fit, estimated before it (``max_object_memory_mb``, fitclass -8)
"""
