#!/bin/bash
# The large galaxies of the outside-model campaign at twice its shear, g = (0.06, -0.04), on the seeds of
# ../outside_metacal_large (from 301): the same galaxies and noise, paired galaxy by galaxy (README.md here).
#
#   benchmarks/campaigns/shear2x_large/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here SIZE_OPTS="--n-galaxies 200 --stamp-size 128 --size-range 0.85 2" RUN_OPTS="--shear 0.06 -0.04" \
    exec "$here/../outside_metacal/run.sh" "$@"
