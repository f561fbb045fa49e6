"""``explorer.html``: one self-contained page to explore the value-space triangle
(docs/definitions.md §11), opened from disk, with no network access.

The page holds the three vertex matrices, the examples' float16 probabilities (base64 of their
raw little-endian bytes, class-major as ``--save-probs`` writes them) and uncertainty maps (shown
on hover, docs/definitions.md §13) and, after a sweep, its metrics at every grid point. Its
scripts (``explorer_rule.js``, ``explorer_triangle.js``, ``explorer.js``; inlined at write
time) recompute the masks of any point of the triangle and any
defer cost c (or none) with the reference's arithmetic in float64: the mixed matrix
``(w_0 C_0 + w_1 C_1) + w_2 C_2`` (the operation order of ``costs.mix_costs``) with the defer row
``(c, …, c)`` below it (``costs.with_defer``), the column shift ``C - max_k' C[k', ·]`` over all
rows, ``Σ_k`` in ascending order, ties to the lowest row (a class before deferring); so its
labels equal ``decide_reference`` on the embedded probabilities, pixel for pixel (255: deferred).
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from costseg.classes import CLASS_NAMES, DEFERRED_COLOUR, PALETTE, ROI_NAMES
from costseg.costs import off_diagonal
from costseg.report.files import png_bytes, write_text

MAX_EMBEDDED = (256, 512)  # (H, W): larger examples are embedded at a reduced resolution
SCRIPTS = ("explorer_rule.js", "explorer_triangle.js", "explorer.js")  # inlined in this order


@dataclass
class ExplorerExample:
    """One example as embedded in the page.

    Attributes:
        name: the image stem.
        image: (h, w, 3) uint8 RGB at the embedded resolution.
        probs: (N, h, w) float16 probabilities, exactly the embedded values.
        labels: (h, w) uint8 train ids (255 ignored) for the page's metrics, or None.
        roi: (h, w) uint8 RoI ids 1..4, or None.
        note: how the embedded pixels relate to the image's ("" when they are all of them).
        uncertainty: name → (h, w) float16 uncertainty map in nats (``entropy``,
            ``mutual_information``; docs/definitions.md §13), shown on hover.
    """

    name: str
    image: np.ndarray
    probs: torch.Tensor
    labels: np.ndarray | None = None
    roi: np.ndarray | None = None
    note: str = ""
    uncertainty: dict[str, torch.Tensor] = field(default_factory=dict)


def embedded(
    name: str,
    image: np.ndarray,
    probs: torch.Tensor,
    labels: np.ndarray | None = None,
    roi: np.ndarray | None = None,
    uncertainty: dict[str, torch.Tensor] | None = None,
) -> ExplorerExample:
    """An example as the page embeds it: at most 256 × 512, else every s-th pixel.

    Args:
        image: (H, W, 3) uint8 RGB.
        probs: (N, H, W) probabilities (rounded to float16 here).
        labels, roi: (H, W) train ids and RoI ids, or None.
        uncertainty: name → (H, W) uncertainty map (rounded to float16 here), or None.

    >>> ex = embedded("a", np.zeros((600, 800, 3), np.uint8), torch.full((19, 600, 800), 0.05))
    >>> tuple(ex.probs.shape), ex.note
    ((19, 200, 267), 'every 3rd pixel of the 600 × 800 image in each direction')
    """
    height, width = probs.shape[-2:]
    step = max(1, math.ceil(height / MAX_EMBEDDED[0]), math.ceil(width / MAX_EMBEDDED[1]))
    probs = probs[:, ::step, ::step].to("cpu", torch.float16).contiguous()
    h, w = probs.shape[-2:]
    note = ""
    if step > 1:
        nth = {2: "2nd", 3: "3rd"}.get(step, f"{step}th")
        note = f"every {nth} pixel of the {height} × {width} image in each direction"
        image = np.asarray(Image.fromarray(image).resize((w, h), Image.Resampling.BOX))
    pick = lambda a: None if a is None else np.ascontiguousarray(a[::step, ::step])  # noqa: E731
    labels, roi = pick(labels), pick(roi)
    maps = {
        k: v[::step, ::step].to("cpu", torch.float16).contiguous()
        for k, v in (uncertainty or {}).items()
    }
    return ExplorerExample(name, np.ascontiguousarray(image), probs, labels, roi, note, maps)


@dataclass
class SweepData:
    """A sweep's metrics at its grid points.

    Attributes:
        weights: (K, 3) barycentric weights of the grid points.
        metrics: ``metrics[metric][class][roi]`` = K values (NaN: undefined).
        note: how the grid was built and measured.
    """

    weights: list[list[float]]
    metrics: dict[str, dict[str, dict[str, list[float]]]]
    note: str = ""


@dataclass
class Marks:
    """Points marked on the triangle: ``(label, (a, b, c))`` each."""

    named: list[tuple[str, list[float]]] = field(default_factory=list)
    targets: list[tuple[str, list[float]]] = field(default_factory=list)
    certified: list[tuple[str, list[float]]] = field(default_factory=list)


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"))
                            .tobytes()).decode("ascii")  # fmt: skip


def _example_json(ex: ExplorerExample) -> dict:
    h, w = ex.probs.shape[-2:]
    return {
        "name": ex.name,
        "height": h,
        "width": w,
        "probs": _b64(ex.probs.numpy()),
        "image": "data:image/png;base64," + base64.b64encode(png_bytes(ex.image)).decode(),
        "labels": None if ex.labels is None else _b64(ex.labels.astype(np.uint8)),
        "roi": None if ex.roi is None else _b64(ex.roi.astype(np.uint8)),
        "note": ex.note,
        "uncertainty": {k: _b64(v.numpy()) for k, v in ex.uncertainty.items()},
    }


def _nan_to_none(values: Sequence[float]) -> list[float | None]:
    return [None if not math.isfinite(v) else float(v) for v in values]


def largest_off_diagonal(vertices: torch.Tensor) -> float:
    """The largest cost of a confusion (an off-diagonal entry) among (V, N, N) matrices: the top
    of the page's defer slider.

    >>> largest_off_diagonal(torch.tensor([[[0.0, 2], [1, 5]], [[0, 3], [1, 0]]]))
    3.0
    """
    return float(off_diagonal(vertices).max())


def page_data(
    examples: Sequence[ExplorerExample],
    vertices: torch.Tensor,
    vertex_names: Sequence[str],
    marks: Marks,
    sweep: SweepData | None,
    notes: Sequence[str],
    defer: float | None = None,
) -> dict:
    """Everything the page's script reads, as one JSON-able dict (``defer``: the defer cost the
    page opens with, None: none)."""
    v = vertices.to(torch.float64).cpu()
    return {
        "classes": list(CLASS_NAMES),
        "palette": PALETTE.tolist(),
        "deferredColour": list(DEFERRED_COLOUR),
        "roiNames": list(ROI_NAMES),
        "vertexNames": list(vertex_names),
        "vertices": v.reshape(-1).tolist(),  # repr of each float64: parsed back exactly
        "defer": None if defer is None else float(defer),
        "deferMax": largest_off_diagonal(v),
        "named": [{"label": s, "w": list(w)} for s, w in marks.named],
        "targets": [{"label": s, "w": list(w)} for s, w in marks.targets],
        "certified": [{"label": s, "w": list(w)} for s, w in marks.certified],
        "sweep": None
        if sweep is None
        else {
            "weights": sweep.weights,
            "note": sweep.note,
            "metrics": {
                m: {c: {r: _nan_to_none(v) for r, v in rois.items()} for c, rois in by.items()}
                for m, by in sweep.metrics.items()
            },
        },
        "notes": list(notes),
        "examples": [_example_json(ex) for ex in examples],
    }


def write_explorer(
    path: str | Path,
    examples: Sequence[ExplorerExample],
    vertices: torch.Tensor,
    vertex_names: Sequence[str],
    named: Sequence[tuple[str, list[float]]] = (),
    sweep: SweepData | None = None,
    marks: Marks | None = None,
    notes: Sequence[str] = (),
    defer: float | None = None,
) -> Path:
    """Write the self-contained ``explorer.html``.

    Args:
        path: the file to write.
        examples: the embedded examples (:func:`embedded`).
        vertices: (3, N, N) the triangle's vertex matrices, exactly as mixed in Python.
        vertex_names: their names.
        named: named rules that are points of the triangle, ``(name, weights)``.
        sweep: metrics of a sweep, or None.
        marks: target and certified points (``named`` is added to them).
        notes: lines shown on the page (source, probabilities, scaling).
        defer: the defer cost the page opens with (``--defer``; its slider runs from 0 to the
            vertices' largest off-diagonal cost), or None: no deferring.

    Returns:
        ``path``.
    """
    marks = marks or Marks()
    marks = Marks([*marks.named, *named], marks.targets, marks.certified)
    data = page_data(examples, vertices, vertex_names, marks, sweep, notes, defer)
    text = json.dumps(data, allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    text = text.replace("</", "<\\/")
    folder = resources.files("costseg.report")
    html = (folder / "explorer.html").read_text(encoding="utf-8")
    script = "\n".join((folder / name).read_text(encoding="utf-8") for name in SCRIPTS)
    page = html.replace("/*COSTSEG_DATA*/", text).replace("/*COSTSEG_SCRIPT*/", script)
    return write_text(path, page)
