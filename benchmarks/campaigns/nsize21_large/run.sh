#!/bin/bash
# The large galaxies of the outside-model campaign with 21 size nodes instead of 7 (--set n_size=21: the size
# marginalisation's spline over three times the nodes, session 50's quadrature error a tenth), on the seeds of
# ../outside_metacal_large (from 301): the same galaxies and noise, paired galaxy by galaxy (README.md here).
#
#   benchmarks/campaigns/nsize21_large/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" RUN_OPTS="--set n_size=21" \
    exec "$here/../outside_metacal/run.sh" "$@"
