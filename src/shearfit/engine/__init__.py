"""The per-object engine: galaxy models, priors, the joint likelihood over exposures, sampling, the estimator.

Takes arrays and :class:`~shearfit.Observation` records, never files: the
layers above (:mod:`shearfit.pipeline`, :mod:`shearfit.app`) read the data and
call :func:`~shearfit.engine.measure.measure_object`.

- :mod:`.profiles`: radial Fourier tables of the truncated exponential and de Vaucouleurs profiles (sec. 3.1)
- :mod:`.priors`: ellipticity, size, bulge-fraction and flux priors (App. B, sec. 3.2)
- :mod:`.moffat`: the circular Moffat that stands for a native PSF above Nyquist (App. A)
- :mod:`.model`: one exposure as Fourier modes: PSF, Jacobian, pixel, alias correction; :func:`render_object`
- :mod:`.likelihood`: the joint likelihood and its bulge-fraction, position and flux marginals (sec. 3.2)
- :mod:`.sampling`: adaptive ellipticity sampling, size marginal, likelihood-mean estimator, weight (3.3-3.5)
- :mod:`.measure`: :func:`measure_object`, star/galaxy classification, the result
- :mod:`.kernel`: the compiled inner loops (or their numpy twins) in use
"""
