#!/usr/bin/env bash
# Issue 68's measurement: one T-push world model of the top and side views against two
# single-view models driven by the same actions (the paper's way), at one budget, resumable:
# `bash bench/two_views.sh` from the repository's root (rerun it after an interruption: a
# collection appends only the episodes its store lacks, a training resumes from its last
# checkpoint). One thread a job; WORKERS=1 collects on one core (default 2).
#   data/broad_two.zarr        the shipped model's episodes (its seeds, data/broad.zarr) seen by both cameras
#   data/broad_top.zarr, data/broad_side.zarr   its views imported alone (the single-view models' data)
#   data/two_views_eval.zarr   16 held-out play-broad episodes x 200 steps of both views (seeds 760000-760015)
#   $OUT/codec_two             one conv-x8-64 codec trained on the frames of both views ($AE steps, default 2000: twice the
#                              shipped codec's; ~3 s a step in float32 on a 2-core AVX2 EPYC)
#   $OUT/dyn_two, dyn_top, dyn_side   stage 2 from scratch on it, $DYN steps each (default 3000; the recipe of
#                              bench/results/ablations.md's pt_dyn_x8_3k: long unrolls, a 10-latent window, bf16);
#                              one latent cache: dyn_two encodes both views, then the single views' runs (side by side)
#                              read theirs from it
# then bench/cross_view.py (the views' disagreement, each view's pose error and PSNR) writes
# bench/results/cross_view. SCALE=tiny shrinks every step to seconds (a smoke test of the chain).
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1
IWSIM=${IWSIM:-.venv/bin/iwsim}
PYTHON=${PYTHON:-.venv/bin/python}
OUT=${OUT:-runs}
DATA=${DATA:-data}
if [ "${SCALE:-full}" = tiny ]; then
    PLAY="--episodes 3 --steps 30" NOISY="--episodes 2 --steps 30" BROAD="--episodes 2 --steps 30"
    HANDS="--episodes 2 --steps 30" EVAL="--episodes 2 --steps 20" AE=${AE:-2} DYN=${DYN:-2} PRESETS="tiny tiny"
    EVALSTEPS=10 FAST=""
else
    PLAY="--episodes 400 --steps 200" NOISY="--episodes 300 --steps 150" BROAD="--episodes 600 --steps 200"
    HANDS="--episodes 300 --steps 150" EVAL="--episodes 16 --steps 200" AE=${AE:-2000} DYN=${DYN:-3000}
    PRESETS="conv-x8-64 pusht-64" EVALSTEPS=192 FAST="--variant long-unroll --context 10 --bf16 --compile"
fi
read -r AE_PRESET DYN_PRESET <<< "$PRESETS"
mkdir -p "$OUT" "$DATA"
step() { echo "== $(date +%H:%M:%S) $*"; }
collect() {  # collect POLICY SEED STORE FLAGS...
    "$IWSIM" collect --task pusht --policy "$1" --seed "$2" --out "$DATA/$3" --cameras top,side \
        --workers "${WORKERS:-2}" --no-progress "${@:4}"
}
step "the broad data's episodes seen by both cameras (its seeds), merged"
collect play 0 two_play.zarr $PLAY
collect expert-noisy 1000 two_expert_noisy.zarr $NOISY
collect play-broad 20000 two_play_broad.zarr $BROAD
collect expert-hands 30000 two_expert_hands.zarr $HANDS
if [ ! -d "$DATA/broad_two.zarr" ]; then
    "$IWSIM" data merge "$DATA/two_play.zarr" "$DATA/two_expert_noisy.zarr" "$DATA/two_play_broad.zarr" \
        "$DATA/two_expert_hands.zarr" --out "$DATA/broad_two.zarr" --no-progress
fi
for view in top side; do
    if [ ! -d "$DATA/broad_$view.zarr" ]; then
        "$IWSIM" data import --format zarr --in "$DATA/broad_two.zarr" --camera "$view" --image-size 64 \
            --out "$DATA/broad_$view.zarr" --no-progress
    fi
done
step "held-out episodes of both views (seeds 760000-)"
collect play-broad 760000 two_views_eval.zarr $EVAL
step "one codec on both views' frames, $AE steps"
"$IWSIM" train ae --data "$DATA/broad_two.zarr" --preset "$AE_PRESET" --steps "$AE" --bf16 --out "$OUT/codec_two" \
    --threads 1 --no-progress
dynamics() {  # dynamics MODEL: stage 2 on data/broad_MODEL.zarr, then the model exported
    "$IWSIM" train dynamics --ae "$OUT/codec_two" --data "$DATA/broad_$1.zarr" --preset "$DYN_PRESET" $FAST \
        --steps "$DYN" --out "$OUT/dyn_$1" --latent-cache "$OUT/latents_two.safetensors" --threads 1 --no-progress
    "$IWSIM" export-model --run "$OUT/dyn_$1" --out "$OUT/wm_$1" --force
}
step "stage 2 of both views, $DYN steps (it encodes the latent cache)"
dynamics two
step "stage 2 of the top view and of the side view, $DYN steps each, side by side (their latents read from the cache)"
dynamics top & top=$!
dynamics side & side=$!
wait "$top"
wait "$side"
step "cross-view consistency"
"$PYTHON" bench/cross_view.py --models joint="$OUT/wm_two" pair="$OUT/wm_top+$OUT/wm_side" \
    --store "$DATA/two_views_eval.zarr" --steps "$EVALSTEPS" --out "${RESULTS:-bench/results/cross_view}"
