"""The applications on top of the library: the ``shearfit`` command and its demos.

- :mod:`.cli`: ``shearfit`` and its sub-commands (``main(argv)`` for tests)
- :mod:`.demo`: ``shearfit demo``: a simulated field through the whole pipeline
- :mod:`.demo_stamps`: ``shearfit demo --stamps``: the engine alone on GalSim postage stamps
"""
