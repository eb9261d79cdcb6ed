#!/bin/bash
# The large galaxies of the outside-model campaign (half-light radii 0.85-2" in 128-pixel stamps, 200 a seed) with
# every metacal version fitted on its own (ring_test.py --metacal-fresh; the pipeline's metacal_replay: false), on
# the seeds of ../outside_metacal_large (from 301): the same galaxies and noise as the shipped setting's, paired
# galaxy by galaxy with
#
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/fresh_metacal_large/seed*.fits --metacal \
#       --snr-min 10 --snr-max 40 --paired-with benchmarks/campaigns/outside_metacal_large/seed*.fits
#
# Its sums are kept here, apart from the shipped setting's (this folder's name is outside outside_metacal*).
#
#   benchmarks/campaigns/fresh_metacal_large/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" RUN_OPTS="--metacal-fresh" \
    exec "$here/../outside_metacal/run.sh" "$@"
