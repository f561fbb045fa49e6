"""Running an exported decision graph with onnxruntime (what ``docs/deploy.md`` shows in NumPy).

``onnxruntime`` is an optional extra (``pip install 'costseg[onnx]'``), imported only here.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

__all__ = ["run_graph", "session_of"]


def session_of(model: str | Path | bytes, threads: int = 0):
    """An onnxruntime CPU session of a graph file or its bytes (``threads`` 0: onnxruntime's
    default, one per core); ValueError when onnxruntime is missing."""
    try:
        import onnxruntime as ort
    except ImportError:
        message = "exported graphs run with onnxruntime: pip install 'costseg[onnx]'"
        raise ValueError(message) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.log_severity_level = 3  # errors only
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])


def run_graph(
    session,
    image: Tensor,
    cost: Tensor,
    priors: Tensor | None = None,
    temperature: float | Tensor = 1.0,
    probabilities: bool = False,
) -> tuple[Tensor, ...]:
    """The graph's labels and margins (and probabilities) for uint8 ``image`` under ``cost``.

    Args:
        session: from :func:`session_of`.
        image: (B, 3, H, W) uint8 RGB.
        cost: (N, N) or (N + 1, N) matrix.
        priors: None (no priors), (N,) global or (N, H, W) pixel-wise priors.
        temperature: the softmax temperature.
        probabilities: also return the graph's probabilities (it must have that output).
    """
    n = cost.shape[1]
    priors = torch.ones(n) if priors is None else priors
    priors = priors.view(n, 1, 1) if priors.ndim == 1 else priors
    feeds = {
        "image": image.cpu().contiguous().numpy(),
        "cost": cost.to("cpu", torch.float32).numpy(),
        "priors": priors.to("cpu", torch.float32).contiguous().numpy(),
        "temperature": torch.as_tensor(temperature, dtype=torch.float32).reshape(()).numpy(),
    }
    names = ["labels", "margin", *(["probabilities"] if probabilities else [])]
    return tuple(torch.from_numpy(out) for out in session.run(names, feeds))
