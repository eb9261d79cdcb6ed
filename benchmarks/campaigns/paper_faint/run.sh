#!/bin/bash
# The paper's population (inside the model family) at target SNR 10-14.14, metacal, 500 galaxies a seed in 48-pixel
# stamps, rotated exposures: is metacal's faint-end bias the outside-model galaxies' own? (README.md here)
#
#   benchmarks/campaigns/paper_faint/run.sh WORKDIR SEED...
#
# RUN_OPTS adds options to each run, with a DEST of its own for their sums, e.g. metacal's round new PSF:
#
#   DEST=benchmarks/campaigns/paper_faint/round RUN_OPTS="--metacal-psf round" \
#       benchmarks/campaigns/paper_faint/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=${DEST:-$here} POPULATION_OPTS="" SIZE_OPTS="--n-galaxies 500" SNR_RANGE="10 14.14" \
    exec "$here/../outside_metacal/run.sh" "$@"
