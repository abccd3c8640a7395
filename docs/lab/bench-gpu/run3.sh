#!/bin/bash
# GPU call 3: candle against PyTorch on the same network and weights (bench-model's export and
# xtask/scripts/torch_yardstick.py), on the H200 and on its 16 CPU cores; one tar back
set -u
G=target/gpu
cd "$(dirname "$0")/../../.."
R=$OUT/r; mkdir -p $R
xz -dc -T0 $G/xtask-cuda.xz > $G/xtask && chmod +x $G/xtask
PY=$(command -v python3)
LIBS=$($PY -c "import site,glob,os;print(':'.join(sorted({d for sp in site.getsitepackages() for d in glob.glob(os.path.join(sp,'nvidia','*','lib'))})))")
export LD_LIBRARY_PATH=$LIBS:${LD_LIBRARY_PATH:-}
{ which nsys ncu; $PY -c "import torch,sys;print(torch.__version__, torch.version.cuda, torch.backends.cudnn.version(), sys.executable)"; lscpu | head -20; } > $R/env.txt 2>&1
timeout 120 $G/xtask bench-model --device cuda --export $R/ys-cuda > $R/candle-cuda.json 2> $R/candle-cuda.log
echo "candle cuda rc $?" >> $R/rc.txt
timeout 120 $PY xtask/scripts/torch_yardstick.py $R/ys-cuda --device cuda > $R/torch-cuda.json 2> $R/torch-cuda.log
echo "torch cuda rc $?" >> $R/rc.txt
for th in 2 16; do
  RAYON_NUM_THREADS=$th timeout 150 $G/xtask bench-model --device cpu --export $R/ys-cpu > $R/candle-cpu$th.json 2> $R/candle-cpu$th.log
  echo "candle cpu$th rc $?" >> $R/rc.txt
  timeout 150 $PY xtask/scripts/torch_yardstick.py $R/ys-cpu --threads $th > $R/torch-cpu$th.json 2> $R/torch-cpu$th.log
  echo "torch cpu$th rc $?" >> $R/rc.txt
done
rm -f $R/ys-*/weights.safetensors
tar -czf $OUT/gpu3.tgz -C $OUT r && rm -rf $R
