"""Running an exported decision graph with onnxruntime (what ``docs/deploy.md`` shows in NumPy).

``onnxruntime`` is an optional extra (``pip install 'costseg[onnx]'``), imported only when a graph
runs (:func:`costseg.networks.onnx.onnx_session`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["run_graph"]


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
        session: from :func:`costseg.networks.onnx.onnx_session`.
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
