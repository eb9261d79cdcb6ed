#!/bin/bash
# The large galaxies of the own-grid metacal campaign: half-light radii 0.85-2" in 128-pixel stamps, 200 galaxies a
# seed, with the sheared versions on their own ellipticity grids and at their own positions (ring_test.py
# --metacal-own-samples --metacal-own-position). The seeds of ../outside_metacal_large (from 301), so that both
# settings measure the same galaxies and noise; its sums are kept here, apart from those (this folder's name keeps
# it out of outside_metacal*). The same loop:
#
#   benchmarks/campaigns/own_grid_metacal_large/run.sh WORKDIR SEED...
#
# Joined with ../own_grid_metacal as one population of half-light radii log-uniform over 0.1-2", and paired
# galaxy by galaxy with the shipped setting's campaign:
#
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/own_grid_metacal*/seed*.fits --metacal \
#       --snr-min 10 --snr-max 40 --hlr-log-uniform 0.1 2 \
#       --paired-with benchmarks/campaigns/outside_metacal*/seed*.fits
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" \
    RUN_OPTS="--metacal-own-samples --metacal-own-position" exec "$here/../outside_metacal/run.sh" "$@"
