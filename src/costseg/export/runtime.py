"""Running an exported decision graph with onnxruntime (what ``docs/deploy.md`` shows in NumPy).

``onnxruntime`` is an optional extra (``pip install 'costseg[onnx]'``), imported only when a graph
runs (:func:`costseg.networks.onnx.onnx_session`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["check_graph_roi", "run_graph"]

ASPECT_TOLERANCE = 0.02
"""How far a RoI map's height / width may lie from the image's (relative) before it is refused:
the graph resizes the map to the image, so a map of another shape would mean another camera."""


def run_graph(
    session,
    image: Tensor,
    cost: Tensor,
    priors: Tensor | None = None,
    temperature: float | Tensor = 1.0,
    probabilities: bool = False,
    roi: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """The graph's labels and margins (and probabilities) for uint8 ``image`` under ``cost``.

    Args:
        session: from :func:`costseg.networks.onnx.onnx_session`.
        image: (B, 3, H, W) uint8 RGB.
        cost: (N, N) or (N + 1, N) matrix; for a regional graph a (K, N, N) or (K, N + 1, N)
            stack (docs/definitions.md §21).
        priors: None (no priors), (N,) global or (N, H, W) pixel-wise priors.
        temperature: the softmax temperature.
        probabilities: also return the graph's probabilities (it must have that output).
        roi: a regional graph's (h, w) RoI ids < K (:func:`check_graph_roi`).
    """
    n = cost.shape[-1]
    priors = torch.ones(n) if priors is None else priors
    priors = priors.view(n, 1, 1) if priors.ndim == 1 else priors
    feeds = {
        "image": image.cpu().contiguous().numpy(),
        "cost": cost.to("cpu", torch.float32).numpy(),
        "priors": priors.to("cpu", torch.float32).contiguous().numpy(),
        "temperature": torch.as_tensor(temperature, dtype=torch.float32).reshape(()).numpy(),
    }
    if "roi" in [i.name for i in session.get_inputs()]:
        feeds["roi"] = check_graph_roi(roi, tuple(image.shape[-2:]), cost).numpy()
    elif roi is not None or cost.ndim != 2:
        raise ValueError(
            "this graph takes one matrix: a regional value system needs a graph exported with "
            "--regional"
        )
    names = ["labels", "margin", *(["probabilities"] if probabilities else [])]
    return tuple(torch.from_numpy(out) for out in session.run(names, feeds))


def check_graph_roi(roi: Tensor | None, size: tuple[int, int], stack: Tensor) -> Tensor:
    """The (h, w) uint8 RoI map a regional graph takes for images of ``size`` (H, W) under a
    (K, M, N) ``stack``: any size of the images' shape (the graph resizes it, nearest), or 1 x 1
    (one RoI everywhere), ids < K.

    Raises:
        ValueError: in one line, a missing map, a stack that is one matrix, a map that is not
            (h, w), of another shape than the images, or with an id that has no matrix.

    >>> check_graph_roi(torch.ones(4, 8), (2, 4), torch.ones(2, 3, 3)).dtype
    torch.uint8
    >>> check_graph_roi(torch.ones(8, 4), (2, 4), torch.ones(2, 3, 3))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: the RoI map is 8 x 4 and the images 2 x 4: a map of the images' shape ...
    """
    if roi is None or stack.ndim != 3:
        raise ValueError(
            "a regional graph takes a stack of matrices (K, N, N) and a RoI map (h, w) uint8"
        )
    roi = torch.as_tensor(roi)
    if roi.ndim != 2 or not roi.numel():
        raise ValueError(f"the RoI map must be (h, w), got {tuple(roi.shape)}")
    (h, w), (height, width) = roi.shape, size
    if roi.numel() > 1 and abs(h * width / (w * height) - 1) > ASPECT_TOLERANCE:
        raise ValueError(
            f"the RoI map is {h} x {w} and the images {height} x {width}: a map of the images' "
            "shape (resized to them, nearest) is needed"
        )
    low, high = int(roi.min()), int(roi.max())
    if low < 0 or high >= len(stack):
        bad = low if low < 0 else high
        raise ValueError(f"the RoI map holds id {bad}; the stack has matrices 0 … {len(stack) - 1}")
    return roi.to("cpu", torch.uint8).contiguous()
