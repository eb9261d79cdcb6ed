#!/bin/bash
# The paper's population (inside the model family) at target SNR 10-40 with the position step capped (session 52),
# metacal, 800 galaxies a seed in 48-pixel stamps, rotated exposures, antithetic twins (README.md here):
#
#   benchmarks/campaigns/stepcap_paper/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=${DEST:-$here} POPULATION_OPTS="" SIZE_OPTS="--n-galaxies 800" exec "$here/../outside_metacal/run.sh" "$@"
