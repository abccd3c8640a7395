#!/usr/bin/env bash
# Candle (`veila bench`) and PyTorch eager (xtask/scripts/torch_yardstick.py) on the same network,
# one training step per batch, each measurement in a fresh process, one after another; prints one
# markdown table: grid, batch, ops, precision, device, peak memory, step time, per-sample memory.
# Run by hand, not by CI.
#
#   xtask/scripts/bench_side_by_side.sh [EXPORT_DIR]
#
# EXPORT_DIR: a `cargo xtask bench-model --network paper --export DIR` folder (default
# target/yardstick-paper; written first when absent). Settings from the environment:
#   BATCHES=1,2  PRECISION=f32  DEVICE=cpu  THREADS=2  TRAIN_RUNS=3
#   CHECKPOINTING=none (or none,block: candle's activation checkpointing, each a row)
#   OPS=fused (or fused,reference: candle also with VEILA_NN_REFERENCE_OPS=1, the ops a GPU runs)
#   VEILA=target/release/veila  PY=/work/venv-torch/bin/python3 (else python3)  OUT=target/side-by-side
# The candle side is `veila bench --models NETWORK` at that network's own grid (`paper`: 64 x 1024),
# so a reduced export (--grid, --base-channels) gives PyTorch rows of another size: the table's grid
# column says which. candle's peak memory is the `peak_memory_mib` of each `veila bench --json` row (its own reading),
# else the peak RSS of the `veila bench` process (GNU time); a `veila bench` without `--no-eval`
# also runs its batch-2 evaluations, so then its figure is only an upper bound for training.
set -euo pipefail

EXPORT=${1:-target/yardstick-paper}
BATCHES=${BATCHES:-1,2}
PRECISION=${PRECISION:-f32}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-2}
TRAIN_RUNS=${TRAIN_RUNS:-3}
CHECKPOINTING=${CHECKPOINTING:-none}
OPS=${OPS:-fused}
VEILA=${VEILA:-target/release/veila}
OUT=${OUT:-target/side-by-side}
if [ -z "${PY:-}" ]; then
  if [ -x /work/venv-torch/bin/python3 ]; then PY=/work/venv-torch/bin/python3; else PY=python3; fi
fi
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$OUT"

if [ ! -f "$EXPORT/export.json" ]; then
  echo "writing the paper network's export to $EXPORT" >&2
  cargo xtask bench-model --network paper --export "$EXPORT" >&2
fi
NETWORK=$("$PY" -c 'import json,sys; print(json.load(open(sys.argv[1]))["network"])' "$EXPORT/export.json")

# candle: one `veila bench` process per batch
if [ -x "$VEILA" ]; then
  no_eval=""
  help=$("$VEILA" bench --help 2>/dev/null || true)
  if grep -q -- '--no-eval' <<< "$help"; then no_eval="--no-eval"; fi
  for ops in ${OPS//,/ }; do
    reference=0; [ "$ops" = reference ] && reference=1
    for ck in ${CHECKPOINTING//,/ }; do
      for b in ${BATCHES//,/ }; do
        for p in ${PRECISION//,/ }; do
          tag="$ops-$ck-b$b-$p"
          j="$OUT/candle-$tag.json"
          rm -f "$j"
          echo "candle ($ops ops, checkpointing $ck): $NETWORK batch $b $p" >&2
          VEILA_NN_REFERENCE_OPS=$reference RAYON_NUM_THREADS=$THREADS \
            /usr/bin/time -f '%M' -o "$OUT/candle-$tag.rss" \
            "$VEILA" bench --device "$DEVICE" --models "$NETWORK" --batch "$b" --precision "$p" \
            --activation-checkpointing "$ck" --train-runs "$TRAIN_RUNS" --forward-runs 1 \
            --no-generate $no_eval --json "$j" --force \
            > "$OUT/candle-$tag.log" 2>&1 || echo "candle $tag failed: see $OUT/candle-$tag.log" >&2
        done
      done
    done
  done
else
  echo "no veila binary at $VEILA (cargo build --release -p veila-cli): candle rows skipped" >&2
fi

# PyTorch: the yardstick runs every batch in a fresh child process
echo "PyTorch: $NETWORK batches $BATCHES $PRECISION" >&2
"$PY" "$HERE/torch_yardstick.py" "$EXPORT" --batch "$BATCHES" --precision "$PRECISION" \
  --device "$DEVICE" --threads "$THREADS" --train-runs "$TRAIN_RUNS" --json > "$OUT/torch.json" \
  || echo "the yardstick failed or its check did not pass: see $OUT/torch.json" >&2

"$PY" - "$OUT" "$NETWORK" "$BATCHES" "$PRECISION" "$DEVICE" "$OPS" "$CHECKPOINTING" <<'EOF'
import json, os, sys
out, network, batches, precisions, device, opses, cks = sys.argv[1:8]
rows = []
for ops in opses.split(","):
  for ck in cks.split(","):
    for p in precisions.split(","):
      for b in [int(x) for x in batches.split(",")]:
        tag = f"{ops}-{ck}-b{b}-{p}"
        j = f"{out}/candle-{tag}.json"
        if not os.path.exists(j):
            continue
        rep = json.load(open(j))
        for r in rep.get("rows", []):
            if r.get("model") != network or r.get("precision") != p:
                continue
            mem, src = r.get("peak_memory_mib"), "veila bench"
            if mem is None:
                try:
                    mem, src = int(open(f"{out}/candle-{tag}.rss").read().split()[-1]) / 1024, "process RSS"
                except (OSError, ValueError, IndexError):
                    mem, src = None, ""
            grid = "x".join(str(g) for g in r["grid"])
            label = "candle" + (", reference ops" if ops == "reference" else "") + (
                ", checkpointing" if ck == "block" else "")
            rows.append(dict(ops=label, grid=grid, batch=b, precision=p, device=device,
                             mem=mem, src=src, ms=r["train_step_ms"]))
t = os.path.join(out, "torch.json")
check = ""
if os.path.exists(t) and os.path.getsize(t) > 0:
    rep = json.loads(open(t).read().strip().splitlines()[-1])
    check = rep.get("output_rel_l2_vs_candle")
    for r in rep.get("rows", []):
        if "error" in r:
            continue
        rows.append(dict(ops=f"PyTorch {rep['torch']}", grid=r["grid"], batch=r["batch"], precision=r["precision"],
                         device=r["device"], mem=r["peak_memory_mib"], src="fresh process", ms=r["step_ms"]))
print(f"| grid | batch | ops | precision | device | peak memory (MiB) | training step (ms) | per-sample memory (MiB) |")
print("|---|---|---|---|---|---|---|---|")
prev = {}
for r in sorted(rows, key=lambda r: (r["ops"], r["precision"], r["batch"])):
    key = (r["ops"], r["precision"])
    ps = ""
    if key in prev and r["mem"] is not None and prev[key]["mem"] is not None:
        ps = f"{(r['mem'] - prev[key]['mem']) / (r['batch'] - prev[key]['batch']):.0f}"
    prev[key] = r
    mem = f"{r['mem']:.0f} ({r['src']})" if r["mem"] is not None else "n/a"
    print(f"| {r['grid']} | {r['batch']} | {r['ops']} | {r['precision']} | {r['device']} | {mem} | {r['ms']:.0f} | {ps} |")
if check != "":
    print(f"\nPyTorch's output against candle's on the exported input: relative L2 {check:.2g}")
EOF
