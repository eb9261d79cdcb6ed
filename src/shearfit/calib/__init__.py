"""Shear calibration: bias estimates, the noise-bias calibration from simulations, metacalibration.

- :mod:`.bias`: m and c from +g/-g pairs with bootstrap errors (one helper for tests, benchmarks and the demo)
- :mod:`.calibrate`: m(SNR, size) fitted on simulations and applied to a catalogue (sec. 8.4)
- :mod:`.metacal`: metacalibration: sheared versions, replayed fits, the response
- :mod:`.noisebias`: the analytic noise-bias model of App. C
- :mod:`.weights`: lensing weights that do not respond to shear (binned on SNR and circularised size)
"""
