"""Any framework's ONNX network as a probability source (``docs/definitions.md §19``).

An ONNX file with one image input, (B, 3, H, W) float (normalised as the spec says) or uint8,
and N-class logits (or, with ``?output=probs``, probabilities) as its first output, at the input
size or a fraction of it, runs under onnxruntime and is resized bilinearly to the input size as
every other network is. A decision graph written by ``scripts/export.py`` is recognised by its
metadata and gives its ``probabilities`` output. ``onnxruntime`` is an optional extra
(``pip install 'costseg[onnx]'``), imported only here and only when such a file is loaded.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from costseg.classes import NUM_CLASSES
from costseg.costs import symmetric_cost
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, ImageNetwork

__all__ = ["GRAPH_METADATA", "load_onnx", "onnx_options", "onnx_session"]

GRAPH_METADATA = "costseg_decision_graph"
"""The metadata key of a graph written by ``scripts/export.py`` (its value: the sidecar JSON)."""
_INPUT_TYPES = {"tensor(float)": np.float32, "tensor(uint8)": np.uint8}


def onnx_options(items: list[tuple[str, str]], spec: str) -> dict[str, Any]:
    """The options after ``onnx:FILE?``: ``mean`` and ``std`` (three numbers on the [0, 1]
    scale of ``image / 255``, comma-separated) and ``output`` (``logits`` or ``probs``).

    >>> onnx_options([("mean", "0.5,0.5,0.5"), ("output", "probs")], "onnx:m.onnx")
    {'mean': (0.5, 0.5, 0.5), 'probabilities': True}
    >>> onnx_options([("mean", "123.7,116.3,103.5")], "onnx:m.onnx")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: bad mean in 'onnx:m.onnx': expected three numbers in [0, 1] (the scale of ...
    """
    options: dict[str, Any] = {}
    for key, value in items:
        if key in ("mean", "std"):
            try:
                triple = tuple(float(v) for v in value.split(","))
            except ValueError:
                triple = ()
            low = 0.0 if key == "mean" else 1e-6  # a std must be positive
            if len(triple) != 3 or not all(low <= v <= 1 for v in triple):
                interval = "[0, 1]" if key == "mean" else "(0, 1]"
                raise ValueError(
                    f"bad {key} in {spec!r}: expected three numbers in {interval} "
                    "(the scale of image / 255; divide 0-255 values by 255)"
                )
            options[key] = triple
        elif key == "output" and value in ("logits", "probs"):
            options["probabilities"] = value == "probs"
        else:
            raise ValueError(f"bad option {key}={value} in {spec!r}: expected mean, std or output")
    return options


class _OnnxLogits(nn.Module):
    """An onnxruntime session as a ``(B, 3, H, W) → (B, N, h, w)`` logits module.

    Args:
        path: the ONNX file.
        session: its CPU session (a CUDA one is opened on the first CUDA input, where
            onnxruntime-gpu is installed).
        feeds: constant inputs besides the image (a decision graph's matrix, priors, temperature).
        output: the output to read; ``probabilities``: it holds probabilities (their log is
            returned, as :meth:`costseg.networks.sources.Source.logits_of` does).
    """

    def __init__(self, path: Path, session, feeds: dict, output: str, probabilities: bool) -> None:
        super().__init__()
        self.path, self.feeds, self.output, self.probabilities = path, feeds, output, probabilities
        self.sessions = {"cpu": session}
        image = session.get_inputs()[0]
        self.input_name, self.dtype = image.name, _INPUT_TYPES[image.type]
        self.fixed = [d if isinstance(d, int) else None for d in image.shape]

    def forward(self, x: Tensor) -> Tensor:
        self._check_size(tuple(x.shape))
        array = x.detach().to("cpu", torch.float32).contiguous().numpy()
        if self.dtype == np.uint8:  # the image unchanged (mean 0, std 1, rescale 1)
            array = array.astype(np.uint8)
        # A graph of a fixed batch of 1 runs image by image.
        parts = [array[i : i + 1] for i in range(len(array))] if self.fixed[0] == 1 else [array]
        session = self._session(x.device)
        try:
            out = [session.run([self.output], {self.input_name: p, **self.feeds})[0] for p in parts]
        except Exception as err:  # onnxruntime raises its own exception types
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            size = " x ".join(str(s) for s in x.shape)
            raise ValueError(f"{self.path} refused a {size} input: {first}") from None
        scores = torch.from_numpy(np.concatenate(out)).float()
        if scores.ndim != 4 or scores.shape[1] != NUM_CLASSES:
            raise ValueError(_classes_message(self.path, scores.shape))
        scores = scores.clamp_min(1e-30).log() if self.probabilities else scores
        return scores.to(x.device)

    def _check_size(self, shape: tuple[int, ...]) -> None:
        fixed_hw = self.fixed[2:]
        if any(f is not None and f != s for f, s in zip(fixed_hw, shape[2:], strict=True)):
            want = " x ".join("any" if f is None else str(f) for f in fixed_hw)
            raise ValueError(
                f"{self.path} accepts only {want} (H x W) images; got {shape[2]} x {shape[3]}"
            )

    def _session(self, device: torch.device):
        import onnxruntime as ort

        if device.type != "cuda" or "CUDAExecutionProvider" not in ort.get_available_providers():
            return self.sessions["cpu"]
        if "cuda" not in self.sessions:
            providers = [("CUDAExecutionProvider", {"device_id": device.index or 0})]
            self.sessions["cuda"] = ort.InferenceSession(str(self.path), providers=providers)
        return self.sessions["cuda"]


def load_onnx(
    path: str | Path,
    mean: tuple[float, ...] = IMAGENET_MEAN,
    std: tuple[float, ...] = IMAGENET_STD,
    probabilities: bool = False,
) -> ImageNetwork:
    """An ONNX network (one image input, 19-class logits or probabilities out) as an
    `ImageNetwork`, normalised by ``mean`` and ``std`` (on ``image / 255``) for a float input.

    Raises:
        FileNotFoundError: no such file.
        ValueError: onnxruntime is not installed, the file is not a readable ONNX model, or the
            graph has other than one image input or does not give 19 classes.

    >>> load_onnx("no/such.onnx")
    Traceback (most recent call last):
    ...
    FileNotFoundError: ONNX file not found: no/such.onnx
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX file not found: {path}")
    session = onnx_session(path)
    metadata = session.get_modelmeta().custom_metadata_map
    if GRAPH_METADATA in metadata:
        net = _decision_graph(path, session)
        return ImageNetwork(net, mean=(0.0,) * 3, std=(1.0,) * 3, rescale=1.0)
    inputs = session.get_inputs()
    if len(inputs) != 1:
        names = ", ".join(i.name for i in inputs)
        raise ValueError(f"{path} has {len(inputs)} inputs ({names}); expected one image input")
    image = inputs[0]
    if image.type not in _INPUT_TYPES or len(image.shape) != 4 or image.shape[1] not in (3, None):
        raise ValueError(
            f"{path}: input {image.name} is {image.type} {image.shape}; expected (B, 3, H, W) "
            "float or uint8"
        )
    output = session.get_outputs()[0]
    classes = output.shape[1] if len(output.shape) == 4 else 0
    if isinstance(classes, int) and classes != NUM_CLASSES:  # a name: checked when it runs
        raise ValueError(_classes_message(path, output.shape))
    net = _OnnxLogits(path, session, {}, output.name, probabilities)
    if image.type == "tensor(uint8)":
        return ImageNetwork(net, mean=(0.0,) * 3, std=(1.0,) * 3, rescale=1.0)
    return ImageNetwork(net, mean=mean, std=std)


def onnx_session(model: str | Path | bytes, threads: int = 0):
    """An onnxruntime CPU session of an ONNX file or its bytes (``threads`` 0: onnxruntime's
    default, one per core); ValueError when onnxruntime is missing or the model is unreadable."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise ValueError("ONNX graphs run with onnxruntime: pip install 'costseg[onnx]'") from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.log_severity_level = 3  # errors only: onnxruntime's warnings are not the user's
    source = model if isinstance(model, bytes) else str(model)
    try:
        return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own exception types
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        shown = "the graph" if isinstance(model, bytes) else model
        raise ValueError(f"{shown} is not a readable ONNX model: {first}") from None


def _decision_graph(path: Path, session) -> _OnnxLogits:
    """A costseg decision graph as a source: its probabilities under temperature 1."""
    if "probabilities" not in [o.name for o in session.get_outputs()]:
        raise ValueError(
            f"{path} is a decision graph without probabilities: to use it as a network, export "
            "it with export.py --probabilities"
        )
    n = NUM_CLASSES
    feeds = {
        "cost": symmetric_cost(n, torch.float32).numpy(),
        "priors": np.ones((n, 1, 1), np.float32),
        "temperature": np.ones((), np.float32),
    }
    if "roi" in [i.name for i in session.get_inputs()]:  # a regional graph: one matrix, RoI 0
        feeds |= {"cost": feeds["cost"][None], "roi": np.zeros((1, 1), np.uint8)}
    return _OnnxLogits(path, session, feeds, "probabilities", probabilities=True)


def _classes_message(path: Path, shape) -> str:
    shown = " x ".join(str(s) for s in shape)
    classes = shape[1] if len(shape) == 4 else "no"
    return (
        f"{path} gives {classes} classes (output {shown}); expected (B, {NUM_CLASSES}, H, W) "
        "logits of the Cityscapes train classes"
    )
