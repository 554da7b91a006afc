#!/usr/bin/env bash
# The whole recipe of checkpoints/pusht-64, resumable: `make rebuild-pusht-64` (or `bash
# checkpoints/pusht-64/recipe.sh`) from the repository's root. About 9 core-hours on a
# 2-core CPU, one thread a job. Rerun it after an interruption, in this or a later session:
# a collection appends only the episodes its store lacks, a training resumes exactly from
# its last checkpoint, and a finished step is skipped. It ends with the rebuilt model in
# $OUT/pusht-64 and its yardstick row in $OUT/yardstick/results.md.
#
# Environment: OUT (default runs/rebuild-pusht-64), DATA (default data); SCALE=tiny shrinks
# every step to seconds (a smoke test of the chain: other weights); WORKERS, the collection
# processes (default 2; 1 at SCALE=tiny); YARDSTICK=0 skips the final yardstick. Steps and
# seeds are those of checkpoints/pusht-64/README.md.
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1
IWSIM=${IWSIM:-iwsim}
PYTHON=${PYTHON:-python}
OUT=${OUT:-runs/rebuild-pusht-64}
DATA=${DATA:-data}
if [ "${SCALE:-full}" = tiny ]; then
    PLAY="--episodes 4 --steps 30" EXPERT="--episodes 3 --steps 30" BROAD="--episodes 4 --steps 30"
    HANDS="--episodes 3 --steps 30" AE=2 DYN1=2 DYN2=4 DEC=2 FT1=2 FT2=2 FT3=2 FT4=2 BATCH="--batch-size 2"
    WORKERS=${WORKERS:-1}  # a pool's spawned workers cost more than a few tiny episodes
else
    PLAY="--episodes 400 --steps 200" EXPERT="--episodes 300 --steps 150"
    BROAD="--episodes 600 --steps 200" HANDS="--episodes 300 --steps 150"
    AE=1000 DYN1=5000 DYN2=10000 DEC=2000 FT1=1800 FT2=1200 FT3=1200 FT4=7200 BATCH="" WORKERS=${WORKERS:-2}
fi
mkdir -p "$OUT" "$DATA"
step() { echo "== $(date +%H:%M:%S) $*"; }
last_step() {  # the step of a run's last checkpoint, 0 before the first
    local link="$1/checkpoints/last"
    if [ -e "$link" ]; then basename "$(readlink -f "$link")" | sed 's/^0*//;s/^$/0/'; else echo 0; fi
}
export_once() {  # export-model RUN -> DIR, unless DIR is already a model
    if [ ! -f "$2/model.safetensors" ]; then "$IWSIM" export-model --run "$1" --out "$2" "${@:3}"; fi
}

step "play episodes (seeds 0-399)"
"$IWSIM" collect --task pusht --policy play $PLAY --image-size 64 --workers $WORKERS --seed 0 \
    --out "$DATA/play.zarr" --no-progress
step "stage 1: the conv-x8-64 codec, $AE steps"
"$IWSIM" train ae --data "$DATA/play.zarr" --preset conv-x8-64 --steps $AE $BATCH --out "$OUT/codec_x8" \
    --threads 1 --no-progress
step "stage 2: long-unroll dynamics, $DYN1 steps, then rerun to $DYN2 (a warm restart: the README says why)"
if [ "$(last_step "$OUT/dyn_x8_long")" -lt $DYN1 ]; then
    "$IWSIM" train dynamics --ae "$OUT/codec_x8" --data "$DATA/play.zarr" --preset pusht-64 --variant long-unroll \
        --steps $DYN1 $BATCH --out "$OUT/dyn_x8_long" --latent-cache "$OUT/latents_x8.safetensors" --threads 1 --no-progress
fi
"$IWSIM" train dynamics --ae "$OUT/codec_x8" --data "$DATA/play.zarr" --preset pusht-64 --variant long-unroll \
    --steps $DYN2 $BATCH --out "$OUT/dyn_x8_long" --latent-cache "$OUT/latents_x8.safetensors" --threads 1 --no-progress
export_once "$OUT/dyn_x8_long" "$OUT/x8long"
step "noisy-expert episodes (seeds 1000-1299), merged with play"
"$IWSIM" collect --task pusht --policy expert-noisy $EXPERT --image-size 64 --workers $WORKERS --seed 1000 \
    --out "$DATA/expert_noisy.zarr" --no-progress
if [ ! -d "$DATA/contact.zarr" ]; then
    "$IWSIM" data merge "$DATA/play.zarr" "$DATA/expert_noisy.zarr" --out "$DATA/contact.zarr" --no-progress
fi
step "stage 3: the decoder on those frames, $DEC steps"
"$IWSIM" train decoder-finetune --world-model "$OUT/x8long" --data "$DATA/contact.zarr" --out "$OUT/dec_contact" \
    --steps $DEC $BATCH --lr 2e-4 --latent-noise 0,0.1 --threads 1 --no-progress
step "stage 2 fine-tunes on the contact data: $FT1, $FT2 and $FT3 steps"
"$IWSIM" train dynamics --init "$OUT/x8long" --data "$DATA/contact.zarr" --preset pusht-64 --steps $FT1 $BATCH \
    --lr 2e-4 --out "$OUT/dyn_x8_contact" --latent-cache "$OUT/latents_x8_contact.safetensors" --threads 1 --no-progress
export_once "$OUT/dyn_x8_contact" "$OUT/wm_contact_dec" --decoder "$OUT/dec_contact"
"$IWSIM" train dynamics --init "$OUT/wm_contact_dec" --data "$DATA/contact.zarr" --preset pusht-64 --steps $FT2 \
    $BATCH --lr 2e-4 --out "$OUT/dyn_contact_more" --latent-cache "$OUT/latents_x8_contact.safetensors" --threads 1 \
    --no-progress
"$IWSIM" train dynamics --init "$OUT/dyn_contact_more" --data "$DATA/contact.zarr" --preset pusht-64 --steps $FT3 \
    $BATCH --lr 2e-4 --out "$OUT/dyn_contact_more2" --latent-cache "$OUT/latents_x8_contact.safetensors" --threads 1 \
    --no-progress
step "the last fine-tune with rest_threshold 0.05 (issue 41; the model shipped before this one)"
export_once "$OUT/dyn_contact_more2" "$OUT/wm_contact_more2" --rest-threshold 0.05
step "broad motion (issue 41): play-broad episodes (seeds 20000-20599), expert-hands (seeds 30000-30299), merged"
"$IWSIM" collect --task pusht --policy play-broad $BROAD --image-size 64 --workers $WORKERS --seed 20000 \
    --out "$DATA/play_broad.zarr" --no-progress
"$IWSIM" collect --task pusht --policy expert-hands $HANDS --image-size 64 --workers $WORKERS --seed 30000 \
    --out "$DATA/expert_hands.zarr" --no-progress
if [ ! -d "$DATA/broad.zarr" ]; then
    "$IWSIM" data merge "$DATA/contact.zarr" "$DATA/play_broad.zarr" "$DATA/expert_hands.zarr" \
        --out "$DATA/broad.zarr" --no-progress
fi
step "the shipped model: a one-second window (10 latents) fine-tuned on the broad data, $FT4 steps, bf16"
"$IWSIM" train dynamics --init "$OUT/wm_contact_more2" --context 10 --data "$DATA/broad.zarr" --preset pusht-64 \
    --steps $FT4 $BATCH --lr 2e-4 --bf16 --out "$OUT/dyn_win10" --latent-cache "$OUT/latents_broad.safetensors" \
    --threads 1 --no-progress
export_once "$OUT/dyn_win10" "$OUT/pusht-64" --novelty-data "$DATA/broad.zarr" --no-progress
if [ "${YARDSTICK:-1}" != 0 ]; then
    step "its yardstick row"
    "$PYTHON" bench/yardstick.py --models rebuilt="$OUT/pusht-64" --out "$OUT/yardstick"
fi
step "done: $OUT/pusht-64"
