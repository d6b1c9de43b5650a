#!/usr/bin/env bash
# The Bi-GRU sampling-strategy / detector-noise ablation (docs/research.md).
#
#   models/ablation/run.sh NAME STEPS --lengths L --noise N
#
# trains runs/ablation/NAME with the length-sampling recipe (the shipped one
# without --floor-contact; the extra flags are appended, and a flag given twice takes
# its last value), resuming from its checkpoint when there is one, then evaluates it on
# S9/S11 with SH and GT 2D input into runs/ablation/NAME/eval_{sh,gt}_STEPS.*.
# Run from the repository root after `cargo build --release -p blapose-train`;
# the data root is $BLAPOSE_DATA or ../shared/data. The runs of the model card:
#   run.sh true 2000 --lengths true --noise residual
#   run.sh uniform 2000 --lengths uniform --noise residual
#   run.sh normal 2000 --lengths normal --noise residual
#   run.sh ansur 2000 --lengths ansur --noise residual    (then 2977)
#   run.sh noise_none 2000 --lengths ansur --noise none   (then 2977)
# Continuations of the shipped Bi-GRU (warm start, the learning rate it had
# reached at step 2977; STEPS counts from the warm start):
#   INIT=models/bone_length_bigru.safetensors LR=1.77e-4 \
#     run.sh cont_scale1 4000 --lengths ansur --noise residual
# Feet kept on the floor when the lengths are replaced (MODEL=gru
# trains the online GRU instead, add its --per-frame-weight 1.0); floor and
# gru_floor are the shipped weights:
#   run.sh floor 2977 --lengths ansur --noise residual --floor-contact
#   run.sh floor_seed4 2977 --lengths ansur --noise residual --floor-contact --seed 4
#   run.sh floor_len128 2977 --lengths ansur --noise residual --floor-contact --seq-len 128 --batch 16
#   run.sh floor_spread3 2977 --lengths ansur --noise residual --floor-contact --ansur-spread 3.0
#   MODEL=gru run.sh gru_floor 2004 --lengths ansur --noise residual --floor-contact --per-frame-weight 1.0
# One flag each on top of floor (yaw and gru_yaw are the shipped weights):
#   run.sh gauss 2977 --lengths ansur --noise gaussian --floor-contact
#   run.sh yaw 2977 --lengths ansur --noise residual --floor-contact --random-yaw
#   MODEL=gru run.sh gru_yaw 2004 --lengths ansur --noise residual --floor-contact --per-frame-weight 1.0 --random-yaw
# A second seed of the shipped recipe; one camera; rectified keypoints:
#   run.sh yaw_seed4 2977 --lengths ansur --noise residual --floor-contact --random-yaw --seed 4
#   MODEL=gru run.sh gru_yaw_seed4 2004 --lengths ansur --noise residual --floor-contact --per-frame-weight 1.0 --random-yaw --seed 4
#   run.sh cam54 2977 --lengths ansur --noise residual --floor-contact --random-yaw --cameras 54138969
#   (then evaluate with `blapose eval ... --cameras 54138969`)
#   run.sh rectify 2977 --lengths ansur --noise residual --floor-contact --random-yaw --rectify
#   MODEL=gru run.sh gru_rectify 2004 --lengths ansur --noise residual --floor-contact --per-frame-weight 1.0 --random-yaw --rectify
#   (evaluate both with `blapose-lab diagnose ... --rectify`; the script's own evals are without it)
# The runs with research options removed since (--detector-gain, camera
# jitter, --precondition, --decouple-size, --noise-scale; docs/research.md,
# "Options tried and removed") need this script and the trainer as of commit
# 237e820; --height-normalized needs the trainer as of commit 46f5f1a.
set -euo pipefail
name=$1; steps=$2; shift 2
bin=./target/release/blapose
out=runs/ablation/$name
mkdir -p "$out"
# The recorded runs drew bodies from every ANSUR person (before the
# many-bodies benchmark held some out); ANSUR_PEOPLE=train for new runs.
common=(--ansur-people "${ANSUR_PEOPLE:-all}" --ansur-spread 2.0 --shift-plane ground --batch 32 --seq-len 64 --lr "${LR:-3e-4}" --lr-decay 0.9
  --epoch-steps 500 --head-lr-scale 0.01 --ema-decay 0.999 --val-every 200 --checkpoint-secs 300 --seed 3)
[ -n "${INIT:-}" ] && common+=(--init-weights "$INIT")
resume=()
[ -f "$out/checkpoint.safetensors" ] && resume=(--resume)
model=${MODEL:-bigru}
RAYON_NUM_THREADS=1 "$bin" train --model "$model" "${common[@]}" "$@" --steps "$steps" --out "$out" "${resume[@]}"
for input in sh gt; do
  "$bin" eval --model "$model" --input "$input" --weights "$out/model.safetensors" \
    --json "$out/eval_${input}_${steps}.json" > "$out/eval_${input}_${steps}.md"
done
