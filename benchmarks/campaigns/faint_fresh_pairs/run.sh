#!/bin/bash
# Paired runs at the faint end: the outside-model galaxies at target SNR 10-14.14 (64-pixel stamps), each seed
# measured twice on the same galaxies and noise by ../outside_metacal/run.sh's loop: with the shipped replays
# (sums in replay/) and with every metacal version fitted on its own (ring_test.py --metacal-fresh; fresh/):
#
#   benchmarks/campaigns/faint_fresh_pairs/run.sh WORKDIR SEED...
#
# One loop per core, with different seeds; the per-object tables stay in WORKDIR/replay and WORKDIR/fresh (a
# stopped run continues from its checkpoint). N_GALAXIES (default 250) galaxies a seed. Read them paired, without
# selection from the tables and with the star cut and lensfit weights from the sums:
#
#   python benchmarks/ring_test.py --from-tables WORKDIR/fresh/out*.fits --metacal --snr-min 10 --snr-max 14.14 \
#       --all-objects --paired-with WORKDIR/replay/out*.fits
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/faint_fresh_pairs/fresh/seed*.fits --metacal \
#       --snr-min 10 --snr-max 14.14 --paired-with benchmarks/campaigns/faint_fresh_pairs/replay/seed*.fits
here=$(cd "$(dirname "$0")" && pwd)
work=$1
shift
export SIZE_OPTS="--n-galaxies ${N_GALAXIES:-250} --stamp-size 64" SNR_RANGE="10 14.14"
for seed in "$@"; do
    DEST=$here/replay RUN_OPTS="" "$here/../outside_metacal/run.sh" "$work/replay" "$seed" || exit $?
    DEST=$here/fresh RUN_OPTS="--metacal-fresh" "$here/../outside_metacal/run.sh" "$work/fresh" "$seed" || exit $?
done
