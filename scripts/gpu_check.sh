#!/usr/bin/env bash
# The GPU figures of issue #13 on a machine with one CUDA GPU, from the repository root:
#   bash scripts/gpu_check.sh CHECKPOINT [OUT_DIR]
# 1. the decision layer's Triton kernel against the float64 reference, on the GPU;
# 2. scripts/bench_decision.py on the GPU: decide ÷ argmax, mixtures ÷ decide at (1, 19, 1024, 2048),
#    and scripts/bench_triton_configs.py: the kernel's block configurations side by side;
# 3. scripts/bench_pipeline.py's full-resolution section: the 231-point sweep per 1024 x 2048 image
#    (8 stand-in scenes), and where a sweep's time goes (cProfile, 4 images);
# 4. one evaluation with every figure, drawn by worker processes from results on the GPU.
# Runs from the source tree (PYTHONPATH=src): no installation needed beyond torch's image.
set -uo pipefail
ckpt=$1
out=${2:-gpu_check}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
echo "CPU cores: $(nproc)"
python tests/decision_kernel_cases.py --device cuda 2>&1 | tail -n 3
python scripts/bench_decision.py --devices cuda | tee "$out/bench_decision.txt"
python scripts/bench_triton_configs.py | tee "$out/triton_configs.txt"
python scripts/bench_pipeline.py --ckpt_path "$ckpt" --sections full-resolution --images 8 \
  | tee "$out/bench_pipeline.txt"
python scripts/toy_as_cityscapes.py /tmp/standin4 --train 1 --val 4 >/dev/null
python - "$ckpt" <<'PY' | tee "$out/sweep_profile.txt"
import cProfile, pstats, sys
from costseg.evaluation.plan import plan
from costseg.evaluation.run import run
from costseg.options import EvalOptions

opts = EvalOptions(ckpt_path=sys.argv[1], data_root="/tmp/standin4", sweep=0.05, num_examples=0,
                   progress=False, overwrite=True, output_dir="/tmp/sweep_profile")
run(plan(opts))  # warm-up
cProfile.run("run(plan(opts))", "/tmp/sweep.prof")
stats = pstats.Stats("/tmp/sweep.prof")
stats.sort_stats("cumulative").print_stats(40)
stats.sort_stats("tottime").print_stats(15)
PY
python - "$ckpt" "$out" <<'PY' | tail -n 3
import sys
from pathlib import Path
from costseg.evaluation.run import evaluate
from costseg.options import EvalOptions

out = Path(sys.argv[2]) / "evaluation"
evaluate(EvalOptions(ckpt_path=sys.argv[1], data_root="/tmp/standin4", sweep=0.25, limit=2,
                     overwrite=True, output_dir=str(out), progress=False))
print(len(list((out / "figures").glob("*.png"))), "figures written")
PY
