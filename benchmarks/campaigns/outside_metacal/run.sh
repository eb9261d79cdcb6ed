#!/bin/bash
# Run seeds of the outside-model metacal campaign one after another and keep each as galaxy sums here.
#
#   benchmarks/campaigns/outside_metacal/run.sh WORKDIR SEED...
#
# Each seed's per-object table (several MB) and its checkpoint go to WORKDIR; a stopped seed continues from its
# checkpoint when run again (--resume). A finished seed is written here as seedNNN.fits and skipped afterwards.
# Run one such loop per core, with different seeds. To keep a stopped seed's galaxies instead of continuing it:
#
#   python benchmarks/ring_test.py --from-tables WORKDIR/outNNN.partial.fits --metacal --snr-min 10 \
#       --snr-max 40 --save-sums benchmarks/campaigns/outside_metacal/seedNNN_part.fits
#
# PYTHON (default python) runs the benchmark: point it, or PYTHONPATH, at a frozen copy of the package if the
# checkout changes while the loop runs. DEST (default this folder) and SIZE_OPTS (default 800 galaxies a seed in
# 64-pixel stamps, which hold half-light radii up to about 0.9") let another campaign share this loop:
# ../outside_metacal_large/run.sh runs the large galaxies in 128-pixel stamps so. RUN_OPTS (default none) adds
# options to each seed's run, e.g. RUN_OPTS=--metacal-fresh with a DEST of its own (the versions fitted on their
# own: a campaign of another setting, whose sums must not join these). SNR_RANGE (default "10 40") is the target SNR
# range of the runs and of their sums (../faint_fresh_pairs runs SNR 10-14.14 so). POPULATION_OPTS (default
# "--population outside"; set but empty: the paper's population) chooses the galaxies (../paper_faint runs the paper's).
set -u
here=$(cd "$(dirname "$0")" && pwd)
bench=$(cd "$here/../.." && pwd)
dest=${DEST:-$here}
py=${PYTHON:-python}
# shellcheck disable=SC2206
size_opts=(${SIZE_OPTS:---n-galaxies 800 --stamp-size 64})
# shellcheck disable=SC2206
run_opts=(${RUN_OPTS:-})
# shellcheck disable=SC2206
snr=(${SNR_RANGE:-10 40})
# shellcheck disable=SC2206
population=(${POPULATION_OPTS---population outside})
work=$1
shift
mkdir -p "$work" "$dest"
for seed in "$@"; do
    id=$(printf "%03d" "$seed")
    if [ -f "$dest/seed$id.fits" ] || [ -f "$dest/seed${id}_part.fits" ]; then
        continue
    fi
    OMP_NUM_THREADS=1 "$py" "$bench/ring_test.py" ${population[@]+"${population[@]}"} "${size_opts[@]}" ${run_opts[@]+"${run_opts[@]}"} \
        --rotate-exposures --metacal --antithetic --snr-min "${snr[0]}" --snr-max "${snr[1]}" --seed "$seed" --processes 1 \
        --out "$work/out$seed.fits" --resume --quiet > "$work/log$seed.txt" 2>&1 || exit $?
    "$py" "$bench/ring_test.py" --from-tables "$work/out$seed.fits" --metacal --snr-min "${snr[0]}" --snr-max "${snr[1]}" \
        --n-bootstrap 2 --save-sums "$dest/seed$id.fits" > /dev/null || exit $?
done
