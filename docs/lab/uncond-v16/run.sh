#!/usr/bin/env bash
# The unconditional v-diffusion runs of docs/lab/uncond-v16/README.md.
# Usage: run.sh WORK_DIR [min-snr|uniform] [FLAG ...] (from the workspace root; the loss weighting
# defaults to min-snr, the first run's; the run to continue is uniform; further flags go to
# train-default as they are, e.g. --clean-share 0.25 since update 21,500). Niced so that builds
# beside it keep their speed.
set -euo pipefail
work="${1:?usage: run.sh WORK_DIR [min-snr|uniform]}"
weighting="${2:-min-snr}"
shift $(( $# < 2 ? $# : 2 ))
exec nice -n 10 cargo run --release -q -p xtask -- train-default --variant unconditional --method v \
  --frames 3000 --scenes scenes/train-v5.txt --encoder-scenes scenes/train-v5.txt \
  --steps 40000 --batch 8 --lr 1e-3 --ema-decay 0.999 --loss-weighting "$weighting" \
  --base-channels 16 --channel-mults 1,2,4,8 --res-blocks 1 \
  --checkpoint-every 250 --snapshot-every 1000 \
  --work "$work" --out "$work/bundle" "$@"
