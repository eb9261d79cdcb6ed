#!/bin/bash
# The large galaxies of the outside-model campaign with four times the ellipticity samples (--set n_above=120: the
# adaptive grid refines until 120 samples, not 30, lie above 5 % of the peak), on the seeds of
# ../outside_metacal_large (from 301): the same galaxies and noise, paired galaxy by galaxy (README.md here).
#
#   benchmarks/campaigns/finegrid_large/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" RUN_OPTS="--set n_above=120" \
    exec "$here/../outside_metacal/run.sh" "$@"
