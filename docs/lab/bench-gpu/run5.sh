#!/bin/bash
# GPU call 5 (issue 45), prepared on 2026-11-27 and 2026-11-28 without a GPU: its figures are pending.
# Candle (`veila bench`, each row a fresh process, device memory sampled by nvidia-smi) and PyTorch
# eager (xtask/scripts/torch_yardstick.py, torch.cuda.max_memory_allocated) on one card, in one call:
# the bundled and the paper network, f32 and bf16, the paper's with and without activation
# checkpointing, at batch 1 and 8 (per-sample memory = the slope). One tar back.
#
#   here:   cargo xtask build-cuda --xtask --pack        # target/cuda/{veila,xtask}-cuda.xz
#   there:  bash docs/lab/bench-gpu/run5.sh                  # carry target/cuda; at most 9.5 minutes
set -u
cd "$(dirname "$0")/../../.."
G=target/cuda
R=$OUT/r; mkdir -p "$R"
for b in veila xtask; do xz -dc -T0 "$G/$b-cuda.xz" > "$G/$b" && chmod +x "$G/$b"; done
PY=$(command -v python3)
LIBS=$($PY -c "import site,glob,os;print(':'.join(sorted({d for sp in site.getsitepackages() for d in glob.glob(os.path.join(sp,'nvidia','*','lib'))})))")
export LD_LIBRARY_PATH=$LIBS:${LD_LIBRARY_PATH:-}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$R/gpu.csv" 2>&1

# step NAME SECONDS CMD...: stdout to NAME.out, stderr to NAME.log, the exit code to rc.txt
step() {
    local name=$1 secs=$2; shift 2
    timeout "$secs" "$@" > "$R/$name.out" 2> "$R/$name.log"
    echo "$name rc $? ($(date -u +%T))" >> "$R/rc.txt"
}

# the CUDA kernels against their compositions (f64 truth on the GPU), errors and milliseconds
step check-kernels 60 "$G/xtask" check-kernels --device cuda --runs 10 --json "$R/check-kernels.json"
# candle
step bench-bundled 80 "$G/veila" bench --device cuda --models bundled --precision f32,bf16 \
    --batch 8 --no-eval --json "$R/bench-bundled.json"
step bench-paper 180 "$G/veila" bench --device cuda --models paper --precision f32,bf16 \
    --activation-checkpointing none,block --batch 1,8 --train-runs 3 --no-eval \
    --json "$R/bench-paper.json"
# PyTorch eager on the same networks (exports from the CUDA xtask: weights, geometry, candle's output)
step export-paper 50 "$G/xtask" bench-model --network paper --device cuda --export "$R/ys-paper"
step torch-paper 120 "$PY" xtask/scripts/torch_yardstick.py "$R/ys-paper" --device cuda \
    --batch 1,8 --precision f32,bf16 --train-runs 3 --json
step export-bundled 30 "$G/xtask" bench-model --network bundled --device cuda --export "$R/ys-bundled"
step torch-bundled 60 "$PY" xtask/scripts/torch_yardstick.py "$R/ys-bundled" --device cuda \
    --batch 8 --precision f32,bf16 --json
rm -f "$R"/ys-*/weights.safetensors
tar -czf "$OUT/gpu5.tgz" -C "$OUT" r && rm -rf "$R"
