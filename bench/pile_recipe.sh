#!/usr/bin/env bash
# Issue 45's pile-sweeping data and codec, resumable: `bash bench/pile_recipe.sh` from the
# repository's root (rerun it after an interruption: a collection appends only the episodes
# its store lacks, a training resumes from its last checkpoint). One thread a job; WORKERS=1
# collects on one core (default 2) to leave the other to another job.
#   data/pile_contact.zarr      400 play (seeds 0-399) + 300 noisy-expert (seeds 1000-1299) episodes x 200 steps
#   data/pile_play_eval.zarr    20 held-out play episodes (seeds 500000-500019)
#   data/pile_expert_eval.zarr  20 held-out expert episodes (seeds 510000-510019)
#   $OUT/pile_codec_x4_$AE      the conv-x4-64 codec (16 x 16 x 8 latents), $AE steps (default 8000)
# then bench/pile_codec.py scores it on the held-out frames (bench/results/pilesweep/codec.md).
# SCALE=tiny shrinks every step to seconds (a smoke test of the chain).
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1
IWSIM=${IWSIM:-.venv/bin/iwsim}
PYTHON=${PYTHON:-.venv/bin/python}
OUT=${OUT:-runs}
DATA=${DATA:-data}
if [ "${SCALE:-full}" = tiny ]; then
    PLAY="--episodes 3 --steps 30" EXPERT="--episodes 2 --steps 30" EVAL="--episodes 2 --steps 20" AE=${AE:-2}
    BATCH="--batch-size 2" WORKERS=${WORKERS:-1}  # a pool's spawned workers cost more than a few tiny episodes
else
    PLAY="--episodes 400 --steps 200" EXPERT="--episodes 300 --steps 200" EVAL="--episodes 20 --steps 200"
    AE=${AE:-8000} BATCH=""
fi
mkdir -p "$OUT" "$DATA"
step() { echo "== $(date +%H:%M:%S) $*"; }
collect() {  # collect POLICY SEED STORE FLAGS...
    "$IWSIM" collect --task pilesweep --policy "$1" --seed "$2" --out "$DATA/$3" --workers "${WORKERS:-2}" --no-progress "${@:4}"
}
step "play (seeds 0-399) and noisy-expert (seeds 1000-1299) episodes, merged"
collect play 0 pile_play.zarr $PLAY
collect expert-noisy 1000 pile_expert_noisy.zarr $EXPERT
if [ ! -d "$DATA/pile_contact.zarr" ]; then
    "$IWSIM" data merge "$DATA/pile_play.zarr" "$DATA/pile_expert_noisy.zarr" --out "$DATA/pile_contact.zarr" \
        --no-progress
fi
step "held-out play (seeds 500000-500019) and expert (seeds 510000-510019) episodes"
collect play 500000 pile_play_eval.zarr $EVAL
collect expert 510000 pile_expert_eval.zarr $EVAL
step "the conv-x4-64 codec, $AE steps"
"$IWSIM" train ae --data "$DATA/pile_contact.zarr" --preset conv-x4-64 --steps "$AE" $BATCH \
    --out "$OUT/pile_codec_x4_$AE" --threads 1 --no-progress
step "the codec on held-out frames"
if [ ! -f "$OUT/pile_codec_x4_$AE.md" ]; then
    "$PYTHON" bench/pile_codec.py "x4_$AE=$OUT/pile_codec_x4_$AE" \
        --data "$DATA/pile_play_eval.zarr" "$DATA/pile_expert_eval.zarr" --out "$OUT/pile_codec_x4_$AE.md"
fi
