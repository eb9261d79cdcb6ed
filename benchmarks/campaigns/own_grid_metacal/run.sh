#!/bin/bash
# The outside-model metacal campaign with the sheared versions on their own ellipticity grids and at their own
# positions (ring_test.py --metacal-own-samples --metacal-own-position; the pipeline's metacal_own_grid and
# metacal_own_position): the same galaxies as ../outside_metacal for the same seeds, another setting, so its sums
# are kept here and must not join those (this folder's name keeps it out of outside_metacal*). The same loop:
#
#   benchmarks/campaigns/own_grid_metacal/run.sh WORKDIR SEED...
#
# Use a WORKDIR of its own (the work files are named by seed). The campaign so far:
#
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/own_grid_metacal/seed*.fits --metacal \
#       --snr-min 10 --snr-max 40
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here RUN_OPTS="--metacal-own-samples --metacal-own-position" exec "$here/../outside_metacal/run.sh" "$@"
