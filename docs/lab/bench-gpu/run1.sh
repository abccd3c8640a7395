#!/bin/bash
# GPU call 1: set up, time the denoiser (issue 12's bench), then train runs/v5-all on the GPU
set -u
T0=$(date +%s)
G=target/gpu
cd "$(dirname "$0")/../../.."
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > $OUT/gpu.txt 2>&1
for b in veila xtask; do xz -dc -T0 $G/$b-cuda.xz > $G/$b && chmod +x $G/$b; done
LIBS=$(python3 - <<'PY'
import site, glob, os
dirs=set()
for sp in site.getsitepackages():
    for d in glob.glob(os.path.join(sp,'nvidia','*','lib')): dirs.add(d)
print(':'.join(sorted(dirs)))
PY
)
export LD_LIBRARY_PATH=$LIBS:${LD_LIBRARY_PATH:-}
echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH" > $OUT/env.txt
ls $(echo $LIBS | tr ':' ' ') >> $OUT/env.txt 2>&1
nproc >> $OUT/env.txt
# 1. issue 12's timing
timeout ${BENCH_S:-150} $G/veila bench --device cuda --models bundled,paper --precision f32,bf16 --batch 8 --json $OUT/bench.json > $OUT/bench.log 2>&1
echo "bench rc $? at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
# the CUDA path end to end: the demo on the GPU (compared with the CPU's on the build machine)
timeout 90 $G/veila demo --device cuda --out $OUT/demo-cuda > $OUT/demo.log 2>&1
echo "demo rc $? at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
# 2. training until the budget's end, then the newest checkpoint comes back
LEFT=$(( ${TOTAL_S:-560} - ( $(date +%s) - T0 ) - 25 ))
MIMALLOC_PURGE_DELAY=-1 timeout --signal=INT $LEFT $G/xtask train-default --device cuda --encoder-scenes scenes/train-v5.txt --work runs/v5-all --out runs/v5-all/bundle > $OUT/train.log 2>&1
echo "train rc $? at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
mkdir -p $OUT/v5-all
cp -r runs/v5-all/. $OUT/v5-all/ 2>/dev/null
# only the newest complete checkpoint of each network (none once the bundle is written)
for d in $OUT/v5-all $OUT/v5-all/mean; do
  [ -d $d ] || continue
  newest=$(ls -d $d/step-* 2>/dev/null | while read s; do [ -f $s/state.json ] && echo $s; done | sort | tail -1)
  for s in $(ls -d $d/step-* 2>/dev/null); do
    if [ "$s" != "$newest" ] || [ -f $OUT/v5-all/bundle/bundle.json ]; then rm -rf $s; fi
  done
done
du -sh $OUT/v5-all >> $OUT/times.txt
