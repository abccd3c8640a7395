#!/usr/bin/env bash
# Issue 55's width lever: docs/lab/uncond-v16's uniform run (R2DM's recipe at the bundle's grid)
# with the U-Net twice as wide (base 32 channels instead of 16), otherwise the same command, so
# that its learning curve compares with the width-16 run's at equal updates and equal wall time.
# Usage: run.sh WORK_DIR [FLAG ...] (from the workspace root; a rerun resumes from the newest
# checkpoint in WORK_DIR; further flags go to train-default as they are).
set -euo pipefail
work="${1:?usage: run.sh WORK_DIR [FLAG ...]}"
shift
exec cargo run --release -q -p xtask -- train-default --variant unconditional --method v \
  --frames 3000 --scenes scenes/train-v5.txt --encoder-scenes scenes/train-v5.txt \
  --steps 40000 --batch 8 --lr 1e-3 --ema-decay 0.999 --loss-weighting uniform \
  --base-channels 32 --channel-mults 1,2,4,8 --res-blocks 1 \
  --checkpoint-every 250 --snapshot-every 1000 \
  --work "$work" --out "$work/bundle" "$@"
