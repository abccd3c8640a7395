#!/bin/bash
# GPU call 4: the cuDNN build (`build-cuda --xtask --cudnn`) against call 2/3's plain one, and
# PyTorch in strict f32 and in TF32; one tar back
set -u
G=target/gpu
cd "$(dirname "$0")/../../.."
R=$OUT/r; mkdir -p $R
for b in veila xtask; do xz -dc -T0 $G/$b-cudnn.xz > $G/$b && chmod +x $G/$b; done
PY=$(command -v python3)
LIBS=$($PY -c "import site,glob,os;print(':'.join(sorted({d for sp in site.getsitepackages() for d in glob.glob(os.path.join(sp,'nvidia','*','lib'))})))")
export LD_LIBRARY_PATH=$LIBS:${LD_LIBRARY_PATH:-}
timeout 100 $G/veila bench --device cuda --models bundled --precision f32,bf16 --batch 8 --json $R/cudnn-bundled-b8.json > $R/cudnn-bundled-b8.log 2>&1
echo "cudnn bundled rc $?" >> $R/rc.txt
timeout 100 $G/veila bench --device cuda --models paper --precision f32,bf16 --batch 2 --no-generate --json $R/cudnn-paper-b2.json > $R/cudnn-paper-b2.log 2>&1
echo "cudnn paper rc $?" >> $R/rc.txt
timeout 100 $G/xtask bench-model --device cuda --export $R/ys > $R/cudnn-candle.json 2> $R/cudnn-candle.log
echo "cudnn candle rc $?" >> $R/rc.txt
timeout 100 $PY xtask/scripts/torch_yardstick.py $R/ys --device cuda > $R/torch-strict.json 2> $R/torch-strict.log
echo "torch strict rc $?" >> $R/rc.txt
timeout 100 $PY xtask/scripts/torch_yardstick.py $R/ys --device cuda --tf32 > $R/torch-tf32.json 2> $R/torch-tf32.log
echo "torch tf32 rc $?" >> $R/rc.txt
timeout 100 $G/veila demo --device cuda --out $R/demo > $R/demo.log 2>&1
echo "demo rc $?" >> $R/rc.txt
rm -rf $R/ys/weights.safetensors $R/demo/*.bin $R/demo/*.exr $R/demo/*.ply $R/demo/*.png
tar -czf $OUT/gpu4.tgz -C $OUT r && rm -rf $R
