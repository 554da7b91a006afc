#!/usr/bin/env bash
# The whole recipe of checkpoints/pilesweep-64, resumable: `make rebuild-pilesweep-64` (or
# `bash checkpoints/pilesweep-64/recipe.sh`) from the repository's root. One thread a job.
# Rerun it after an interruption, in this or a later session: a collection appends only the
# episodes its store lacks, a training resumes from its last checkpoint, and a finished step
# is skipped. It ends with the rebuilt model in $OUT/pilesweep-64 and its yardstick row in
# $OUT/yardstick/results.md.
#
# Environment: OUT (default runs/rebuild-pilesweep-64), DATA (default data); SCALE=tiny
# shrinks every step to seconds (a smoke test of the chain: other weights); YARDSTICK=0
# skips the final yardstick.
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1
IWSIM=${IWSIM:-iwsim}
PYTHON=${PYTHON:-python}
OUT=${OUT:-runs/rebuild-pilesweep-64}
DATA=${DATA:-data}
if [ "${SCALE:-full}" = tiny ]; then
    AE=2 DYN=4 FIRST=4 DEC=2 WIN=2 BATCH="--batch-size 2"
else
    AE=8000 DYN=3000 FIRST=250 DEC=1000 WIN=1500 BATCH=""
fi
step() { echo "== $(date +%H:%M:%S) $*"; }
export_once() {  # export-model RUN -> DIR, unless DIR is already a model
    if [ ! -f "$2/model.safetensors" ]; then "$IWSIM" export-model --run "$1" --out "$2" "${@:3}"; fi
}

step "the pile stores and the conv-x4-64 codec, $AE steps (bench/pile_recipe.sh)"
OUT="$OUT" DATA="$DATA" AE=$AE IWSIM="$IWSIM" PYTHON="$PYTHON" bash bench/pile_recipe.sh
step "stage 2: long-unroll dynamics in bf16, $DYN steps"
"$IWSIM" train dynamics --ae "$OUT/pile_codec_x4_$AE" --data "$DATA/pile_contact.zarr" --preset pusht-64 \
    --variant long-unroll --bf16 --steps $DYN $BATCH --out "$OUT/pile_dyn" \
    --latent-cache "$OUT/latents_pile_x4_bf16.safetensors" --threads 1 --no-progress
step "stage 3: the decoder, symmetric foreground weight, $DEC steps (from the dynamics' first checkpoint: it reads only its codec and latent statistics)"
"$IWSIM" train decoder-finetune --world-model "$OUT/pile_dyn/checkpoints/$(printf %08d $FIRST)" \
    --data "$DATA/pile_contact.zarr" --out "$OUT/pile_dec_sym" --steps $DEC --lr 2e-4 --latent-noise 0,0.1 \
    --symmetric-foreground $BATCH --threads 1 --no-progress
export_once "$OUT/pile_dyn/checkpoints/$(printf %08d $DYN)" "$OUT/pile_wm_$DYN" \
    --decoder "$OUT/pile_dec_sym/checkpoints/$(printf %08d $DEC)"
step "stage 2 again: a one-second window (10 latents) fine-tuned from that model, $WIN steps"
"$IWSIM" train dynamics --init "$OUT/pile_wm_$DYN" --context 10 --data "$DATA/pile_contact.zarr" \
    --preset pusht-64 --bf16 --lr 2e-4 --steps $WIN $BATCH --out "$OUT/pile_dyn_win10" \
    --latent-cache "$OUT/latents_pile_x4_bf16.safetensors" --threads 1 --no-progress
step "the model: the trust signal of its data, a scene at rest stays at rest, changes under 0.06 are none"
export_once "$OUT/pile_dyn_win10/checkpoints/$(printf %08d $WIN)" "$OUT/pilesweep-64" \
    --novelty-data "$DATA/pile_contact.zarr" --rest-threshold 0.05 --delta-deadband 0.06 --no-progress
if [ "${YARDSTICK:-1}" != 0 ]; then
    step "the yardstick"
    "$PYTHON" bench/pile_yardstick.py --models "rebuilt=$OUT/pilesweep-64" --horizon 199 \
        --work "$OUT/yardstick_work" --out "$OUT/yardstick"
fi
