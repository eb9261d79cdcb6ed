#!/bin/bash
# Paired runs at the faint end: the outside-model galaxies at target SNR 10-14.14 (64-pixel stamps), each seed
# measured twice on the same galaxies and noise, with the shipped replays (outNNN_replay.fits) and with every
# metacal version fitted on its own (outNNN_fresh.fits, ring_test.py --metacal-fresh):
#
#   benchmarks/campaigns/faint_fresh_pairs/run.sh WORKDIR SEED...
#
# One loop per core, with different seeds. The per-object tables stay in WORKDIR (a stopped run continues from
# its checkpoint); each finished run's galaxy sums (star cut, lensfit weights) are written here as
# seedNNN_replay.fits and seedNNN_fresh.fits. N_GALAXIES (default 250) galaxies a seed. Read them paired:
#
#   python benchmarks/ring_test.py --from-tables WORKDIR/out*_fresh.fits --metacal --snr-min 10 --snr-max 14.14 \
#       --all-objects --paired-with WORKDIR/out*_replay.fits
#   python benchmarks/ring_test.py --from-tables benchmarks/campaigns/faint_fresh_pairs/seed*_fresh.fits --metacal \
#       --snr-min 10 --snr-max 14.14 --paired-with benchmarks/campaigns/faint_fresh_pairs/seed*_replay.fits
set -u
here=$(cd "$(dirname "$0")" && pwd)
bench=$(cd "$here/../.." && pwd)
py=${PYTHON:-python}
work=$1
shift
mkdir -p "$work"
for seed in "$@"; do
    id=$(printf "%03d" "$seed")
    for kind in replay fresh; do
        [ -f "$here/seed${id}_$kind.fits" ] && continue
        opts=()
        [ "$kind" = fresh ] && opts=(--metacal-fresh)
        OMP_NUM_THREADS=1 "$py" "$bench/ring_test.py" --population outside --n-galaxies "${N_GALAXIES:-250}" \
            --stamp-size 64 --rotate-exposures --metacal --antithetic --snr-min 10 --snr-max 14.14 --seed "$seed" \
            --processes 1 ${opts[@]+"${opts[@]}"} --out "$work/out${seed}_$kind.fits" --resume --quiet \
            > "$work/log${seed}_$kind.txt" 2>&1 || exit $?
        "$py" "$bench/ring_test.py" --from-tables "$work/out${seed}_$kind.fits" --metacal --snr-min 10 \
            --snr-max 14.14 --n-bootstrap 2 --save-sums "$here/seed${id}_$kind.fits" > /dev/null || exit $?
    done
done
