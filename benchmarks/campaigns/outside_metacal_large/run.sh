#!/bin/bash
# The outside-model campaign's large galaxies: half-light radii 0.85-2" in 128-pixel stamps, 200 galaxies a seed
# (the 64-pixel stamps of ../outside_metacal hold up to about 0.9"). The same loop, the seeds kept here:
#
#   benchmarks/campaigns/outside_metacal_large/run.sh WORKDIR SEED...
#
# Use seeds and a WORKDIR of their own (the work files are named by seed). Joined with the small galaxies as one
# population of half-light radii log-uniform over 0.1-2":
#
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/outside_metacal*/seed*.fits --metacal \
#       --snr-min 10 --snr-max 40 --hlr-log-uniform 0.1 2
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" exec "$here/../outside_metacal/run.sh" "$@"
