"""Survey statistics of a shear catalogue.

- :mod:`.systematics`: PSF-galaxy cross-correlation against SNR and size, weight bias (sec. 7)
- :mod:`.twopoint`: calibrated xi+ and xi- with TreeCorr, 1 + K, the calibration's covariance (sec. 8.5)
"""
