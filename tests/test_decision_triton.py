"""The decision layer's Triton kernel (its GPU path) equals the float64 reference.

Without a GPU, Triton's interpreter runs the kernel on the CPU (``TRITON_INTERPRET=1``, set
before Triton is imported, hence a fresh process); with one, the same cases run on it.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("triton")
CASES = Path(__file__).parent / "decision_kernel_cases.py"


def test_kernel_under_the_interpreter_equals_the_reference():
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    done = subprocess.run([sys.executable, str(CASES)], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_kernel_on_the_gpu_equals_the_reference():
    done = subprocess.run([sys.executable, str(CASES), "--device", "cuda"], capture_output=True)
    assert done.returncode == 0, done.stderr[-3000:]
