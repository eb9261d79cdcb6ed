#!/bin/bash
# The outside-model metacal campaign (../outside_metacal: half-light radii 0.1-0.9" in 64-pixel stamps, 800
# galaxies a seed, target SNR 10-40, the shipped replays) run again after session 52 capped each model's position
# step at a pixel (position_max_step): the same seeds, so the same galaxies and noise, paired galaxy by galaxy with
# the campaign made before the cap:
#
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/stepcap_outside/seed*.fits --metacal \
#       --snr-min 10 --snr-max 40 --paired-with benchmarks/campaigns/outside_metacal/seed*.fits
#
# Its sums are kept here, apart from the earlier engine's (this folder's name is outside outside_metacal*).
#
#   benchmarks/campaigns/stepcap_outside/run.sh WORKDIR SEED...
here=$(cd "$(dirname "$0")" && pwd)
DEST=$here exec "$here/../outside_metacal/run.sh" "$@"
