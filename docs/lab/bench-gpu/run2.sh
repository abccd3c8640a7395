#!/bin/bash
# GPU call 2: issue 12's timings (bundled at batch 8; the paper's network at batches 1-8) with the
# device memory polled beside them; everything comes back in one tar (the file count is limited)
set -u
T0=$(date +%s)
G=target/gpu
cd "$(dirname "$0")/../../.."
R=$OUT/r; mkdir -p $R
xz -dc -T0 $G/veila-cuda.xz > $G/veila && chmod +x $G/veila
LIBS=$(python3 -c "import site,glob,os;print(':'.join(sorted({d for sp in site.getsitepackages() for d in glob.glob(os.path.join(sp,'nvidia','*','lib'))})))")
export LD_LIBRARY_PATH=$LIBS:${LD_LIBRARY_PATH:-}
nvidia-smi > $R/nvidia-smi.txt 2>&1
nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv,noheader -lms 100 > $R/mem.csv 2>&1 &
POLL=$!
stamp() { echo "$1 $(date +%s.%N)" >> $R/marks.txt; }
stamp start
timeout 120 $G/veila bench --device cuda --models bundled --precision f32,bf16 --batch 8 --json $R/bundled-b8.json > $R/bundled-b8.log 2>&1
echo "bundled rc $?" >> $R/rc.txt; stamp bundled-done
for b in 1 2 4 8; do
  timeout 100 $G/veila bench --device cuda --models paper --precision f32,bf16 --batch $b --no-generate --json $R/paper-b$b.json > $R/paper-b$b.log 2>&1
  echo "paper b$b rc $?" >> $R/rc.txt; stamp paper-b$b-done
  [ $(( $(date +%s) - T0 )) -gt 400 ] && break
done
# the bundled network's update at the batches a GPU would train with
for b in 32 128; do
  timeout 60 $G/veila bench --device cuda --models bundled --precision f32,bf16 --batch $b --no-generate --json $R/bundled-b$b.json > $R/bundled-b$b.log 2>&1
  echo "bundled b$b rc $?" >> $R/rc.txt; stamp bundled-b$b-done
  [ $(( $(date +%s) - T0 )) -gt 480 ] && break
done
kill $POLL
tar -czf $OUT/gpu2.tgz -C $OUT r && rm -rf $R
