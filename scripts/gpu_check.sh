#!/usr/bin/env bash
# The GPU figures of the README, on a machine with one CUDA GPU, from the repository root:
#   bash scripts/gpu_check.sh [OUT_DIR]
# 1. scripts/bench_decision.py: the decision layer at (1, 19, 1024, 2048) on the CPU and the GPU;
#    scripts/bench.py: the Cityscapes config's training step (crop 768, batch 8, bf16);
# 2. `python train.py --config configs/cityscapes.yaml` end to end (full-resolution PNG loading,
#    augmentation, bf16, validation) for 200 steps on procedural scenes written in Cityscapes'
#    layout, and its images/s between logged steps.
set -euo pipefail
out=${1:-gpu_check}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python scripts/bench_decision.py | tee "$out/bench.txt"
python scripts/bench.py --skip-network | tee -a "$out/bench.txt"
python scripts/toy_as_cityscapes.py /tmp/toy_cityscapes --train 320 --val 16
start=$(date +%s)
python train.py --config configs/cityscapes.yaml --data.init_args.root /tmp/toy_cityscapes \
  --trainer.max_steps 200 --trainer.val_check_interval 200 --trainer.log_every_n_steps 25 \
  --trainer.enable_progress_bar false --trainer.logger.init_args.save_dir "$out/runs" \
  2>&1 | grep -v Warning | tail -n 25
echo "train.py, 200 steps + 1 validation: $(($(date +%s) - start)) s wall"
python - "$out/runs" <<'EOF' | tee -a "$out/bench.txt"
import sys
from pathlib import Path
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

run = EventAccumulator(str(next(Path(sys.argv[1]).rglob("events.out.*")).parent))
run.Reload()
loss = run.Scalars("train/loss")
(s0, t0), (s1, t1) = (loss[1].step, loss[1].wall_time), (loss[-1].step, loss[-1].wall_time)
print(f"train.py, Cityscapes config end to end (steps {s0}-{s1}, batch 8, crop 768, bf16): "
      f"{8 * (s1 - s0) / (t1 - t0):.1f} images/s; val mIoU {run.Scalars('val/miou')[-1].value:.3f}")
EOF
