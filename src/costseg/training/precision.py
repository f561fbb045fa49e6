"""The training precision, chosen by the machine unless the config or command line sets it.

bf16 autocast pays only where the hardware computes in bf16: a CUDA GPU that supports it, or a
CPU with AVX512-BF16 or AMX. Elsewhere (AVX2 laptops and most cloud VMs) PyTorch emulates bf16 and
a training step is many times slower than in float32 (docs/speed.md), so those train in 32-bit.
An explicit ``--trainer.precision`` (or a ``precision`` key in the config) always wins.
"""

from __future__ import annotations

import torch


def cpu_has_native_bf16() -> bool:
    """True when this CPU computes bf16 in hardware (AVX512-BF16 or AMX tiles)."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def cuda_has_native_bf16() -> bool:
    """True when a CUDA GPU is present and supports bf16 (Ampere and newer)."""
    return torch.cuda.is_available() and torch.cuda.is_bf16_supported()


def choose_precision(accelerator: object) -> tuple[str, str]:
    """The precision for ``accelerator`` (the trainer's setting) and why, in a few words.

    >>> choose_precision("mps")
    ('32-true', 'no bf16 autocast on mps')
    """
    name = str(accelerator).lower()
    if name in ("gpu", "cuda") or (name == "auto" and torch.cuda.is_available()):
        if cuda_has_native_bf16():
            return "bf16-mixed", "this GPU computes bf16 natively"
        return "32-true", "this GPU has no native bf16"
    if name not in ("cpu", "auto"):
        return "32-true", f"no bf16 autocast on {name}"
    if cpu_has_native_bf16():
        return "bf16-mixed", "this CPU computes bf16 natively (AVX512-BF16 or AMX)"
    capability = torch.backends.cpu.get_cpu_capability()
    return "32-true", f"this CPU ({capability}) has no native bf16; emulated bf16 is far slower"
