#!/usr/bin/env bash
# Issue 64 item 3: T-push data at the paper's scale (10,000 episodes of the families people and
# policies produce) and stage 2 from scratch on it, resumable: `bash bench/paper_scale.sh` from the
# repository's root (rerun it after an interruption: a collection appends only the episodes its
# store lacks, the encoding resumes from the latents it saved, a training from its last checkpoint).
# One change against bench/results/ablations.md's `pt_dyn_x8_3k`: the same codec (the shipped one),
# recipe (long unrolls with the gradient cut, a 10-latent window) and steps, on 10,000 episodes
# instead of data/broad.zarr's 1600. WORKERS=1 collects on one core (default 2).
#   data/paper_play_broad.zarr    5000 x 200 steps of play-broad (seeds 1000000-1004999)
#   data/paper_expert_hands.zarr  3000 x 150 of expert-hands (seeds 1100000-1102999)
#   data/paper_play_press.zarr    2000 x 200 of play-press, setpoints well ahead of blocked pushers
#                                 (seeds 1200000-1201999)
#   data/paper.zarr               the three merged: 10,000 episodes, ~1.85M frames
#   $OUT/pt_dyn_$NAME             stage 2 from scratch on the codec $AE, $DYN steps (default 3000; ~5 h
#                                 to encode the frames by the shipped codec in float32 on a 2-core AVX2
#                                 EPYC, ~55 min in bf16 on 2 cores of a Xeon with AMX)
#   $OUT/wm_$NAME                 the model, then the yardstick's core and contact-then-rest parts
#                                 ($OUT/ys_$NAME; the same parts of x8_3000 are ablations.md's row)
# AE (default checkpoints/pusht-64, the shipped codec) and NAME (default paper) pick another codec, e.g.
# the x4 one: `iwsim wip restore --wip checkpoints/wip/pt_codec_x4_8000 --out runs/pt_codec_x4_8000`, then
# `AE=runs/pt_codec_x4_8000 NAME=paper_x4 bash bench/paper_scale.sh` (its latents: ~7.6 GB in bf16).
# Measured on a 2-core Xeon with AMX, one worker: ~56 play-broad or play-press and ~66 expert-hands
# episodes a minute (~2.8 h for the 10,000 on one core), the merge ~8 min.
# SCALE=tiny shrinks every step to seconds (a smoke test of the chain), under runs/paper_tiny unless
# OUT and DATA say otherwise, so it never meets the full run's stores and checkpoints.
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
IWSIM=${IWSIM:-.venv/bin/iwsim}
PYTHON=${PYTHON:-.venv/bin/python}
if [ "${SCALE:-full}" = tiny ]; then
    OUT=${OUT:-runs/paper_tiny} DATA=${DATA:-runs/paper_tiny/data}
    BROAD="--episodes 2 --steps 30" HANDS="--episodes 2 --steps 30" PRESS="--episodes 2 --steps 30" DYN=${DYN:-2}
    PRESET=tiny FAST="" YARDSTICK=${YARDSTICK:-0}
else
    BROAD="--episodes 5000 --steps 200" HANDS="--episodes 3000 --steps 150" PRESS="--episodes 2000 --steps 200"
    DYN=${DYN:-3000} PRESET=pusht-64 FAST="--variant long-unroll --context 10 --bf16 --compile"
fi
OUT=${OUT:-runs}
DATA=${DATA:-data}
AE=${AE:-checkpoints/pusht-64}
NAME=${NAME:-paper}
mkdir -p "$OUT" "$DATA"
step() { echo "== $(date +%H:%M:%S) $*"; }
collect() {  # collect POLICY SEED STORE FLAGS...
    "$IWSIM" collect --task pusht --policy "$1" --seed "$2" --out "$DATA/$3" --workers "${WORKERS:-2}" \
        --no-progress "${@:4}"
}
step "10,000 episodes: play-broad, expert-hands, play-press"
collect play-broad 1000000 paper_play_broad.zarr $BROAD
collect expert-hands 1100000 paper_expert_hands.zarr $HANDS
collect play-press 1200000 paper_play_press.zarr $PRESS
if [ ! -d "$DATA/paper.zarr" ]; then
    "$IWSIM" data merge "$DATA/paper_play_broad.zarr" "$DATA/paper_expert_hands.zarr" "$DATA/paper_play_press.zarr" \
        --out "$DATA/paper.zarr" --no-progress
fi
step "stage 2 from scratch on the codec $AE, $DYN steps"
"$IWSIM" train dynamics --ae "$AE" --data "$DATA/paper.zarr" --preset "$PRESET" $FAST --steps "$DYN" \
    --out "$OUT/pt_dyn_$NAME" --latent-cache "$OUT/latents_$NAME.safetensors" --threads "${THREADS:-2}" --no-progress
"$IWSIM" export-model --run "$OUT/pt_dyn_$NAME" --out "$OUT/wm_$NAME" --force
if [ "${YARDSTICK:-1}" = 1 ]; then
    step "the yardstick's core and contact-then-rest parts"
    if [ ! -d "$DATA/play_eval.zarr" ]; then
        "$IWSIM" collect --task pusht --policy play --episodes 20 --steps 200 --workers "${WORKERS:-2}" --seed 900000 \
            --out "$DATA/play_eval.zarr" --no-progress
    fi
    "$PYTHON" bench/yardstick.py --models "$NAME$DYN=$OUT/wm_$NAME" --parts core,rest --work "$OUT/ys" \
        --out "$OUT/ys_$NAME" --threads 1
fi
step "done: $OUT/wm_$NAME"
