#!/usr/bin/env bash
# The conditional v-diffusion run of docs/lab/cond-v16/README.md: the unconditional run's final
# network (docs/lab/uncond-v16, update 40,000) given the camera through zero-initialised GCMA
# layers and the bundled model's frozen encoders, then trained on the same 3,000 frames with
# their images. Usage: run.sh WORK_DIR INIT_BUNDLE [FLAG ...] (from the workspace root; further
# flags go to train-default as they are). A rerun resumes from the newest checkpoint in WORK_DIR.
# Niced so that builds beside it keep their speed.
set -euo pipefail
work="${1:?usage: run.sh WORK_DIR INIT_BUNDLE}"
init="${2:?usage: run.sh WORK_DIR INIT_BUNDLE}"
shift 2
exec nice -n 10 cargo run --release -q -p xtask -- train-default --variant full --method v \
  --frames 3000 --scenes scenes/train-v5.txt --encoders-from models/default \
  --init-from "$init" \
  --steps 16000 --batch 8 --lr 2e-4 --ema-decay 0.999 --loss-weighting uniform --clean-share 0.25 \
  --base-channels 16 --channel-mults 1,2,4,8 --res-blocks 1 \
  --checkpoint-every 250 --snapshot-every 1000 \
  --work "$work" --out "$work/bundle" "$@"
