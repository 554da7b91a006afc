#!/usr/bin/env bash
# Issue 68's policy target: Diffusion Policy on two views (top and side) against one view (top),
# trained on the same demonstrations and scored in MuJoCo from the same first states. Resumable:
# `bash bench/two_view_policy.sh` from the repository's root (rerun it after an interruption: the
# demonstrations resume, a training resumes from its last checkpoint, a finished step is skipped).
#   data/demos_two.zarr   the policy-evaluation study's recipe of MuJoCo expert demonstrations
#                         (candidates from seed 0, 300-step takes kept at IoU 0.9 with a 10-step tail),
#                         seen by both cameras: its top view is that of the study's sim_expert.zarr
#   data/demos_top.zarr   its top view alone
#   $OUT/dp_two, dp_top   Diffusion Policy (preset dp) on the first $DEMOS of each, $STEPS steps, seed 0
#   $OUT/dp_{two,top}_eval  each scored in MuJoCo: $EPISODES first states from seed 100000, $HORIZON steps
# then bench/compare_policies.py compares them state by state (bench/results/two_view_policy).
# ~4 core-hours on a 2-core AMD EPYC (float32); SCALE=tiny shrinks every step to seconds.
set -euo pipefail
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1
IWSIM=${IWSIM:-.venv/bin/iwsim}
OUT=${OUT:-runs}
DATA=${DATA:-data}
if [ "${SCALE:-full}" = tiny ]; then
    DEMOS=2 TAKE=12 STEPS=2 EPISODES=2 HORIZON=6 PRESET=tiny-dp ACCEPT="--accept-iou 0"
else
    DEMOS=100 TAKE=300 STEPS=3000 EPISODES=50 HORIZON=600 PRESET=dp ACCEPT=""
fi
mkdir -p "$OUT" "$DATA"
step() { echo "== $(date +%H:%M:%S) $*"; }
step "demonstrations seen by both cameras"
"$IWSIM" demos --task pusht --episodes "$DEMOS" --steps "$TAKE" --seed 0 --max-attempts $((2 * DEMOS)) \
    --give-up-after 32 $ACCEPT --cameras top,side --out "$DATA/demos_two.zarr" --no-progress
if [ ! -d "$DATA/demos_top.zarr" ]; then
    "$IWSIM" data import --format zarr --in "$DATA/demos_two.zarr" --camera top --image-size 64 \
        --out "$DATA/demos_top.zarr" --no-progress
fi
train() {  # train VIEWS: one training, one thread
    "$IWSIM" train policy --policy dp --preset "$PRESET" --data "$DATA/demos_$1.zarr:$DEMOS" --steps "$STEPS" \
        --out "$OUT/dp_$1" --threads 1 --no-progress
}
step "Diffusion Policy on two views and on the top view, $STEPS steps each, side by side"
train two & pid=$!
train top
wait $pid
for views in two top; do
    if [ ! -f "$OUT/dp_${views}_eval/results.json" ]; then
        step "dp_$views in MuJoCo: $EPISODES first states x $HORIZON steps"
        "$IWSIM" eval policy --checkpoint "$OUT/dp_$views" --env mujoco --episodes "$EPISODES" --seed 100000 \
            --steps "$HORIZON" --videos 2 --out "$OUT/dp_${views}_eval" --threads 1 --no-progress &
    fi
done
wait
step "the two policies compared on the same first states"
"${PYTHON:-.venv/bin/python}" bench/compare_policies.py two="$OUT/dp_two_eval" top="$OUT/dp_top_eval" \
    --out "${RESULTS:-bench/results/two_view_policy}"
