"""Result files: text, JSON, CSV and figures, each written atomically by
:func:`costseg.atomic.write_bytes` (parent folders created, never a half-written file)."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from costseg.atomic import write_bytes

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn, not with the writers
    from matplotlib.figure import Figure


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_text(Path(d) / "a" / "b.txt", "hi").read_text()
    'hi'
    """
    return write_bytes(path, text.encode("utf-8"))


def to_jsonable(obj: Any) -> Any:
    """Plain-Python copy of ``obj`` for JSON: NaN and ±inf become ``None`` (JSON ``null``).

    Numpy and torch scalars become numbers, arrays and tensors nested lists, tuples lists,
    paths strings. Mapping keys that are numpy/torch scalars become Python scalars.

    >>> to_jsonable({"p": float("nan"), "n": np.int64(3), "t": torch.tensor([0.5, 1.0])})
    {'p': None, 'n': 3, 't': [0.5, 1.0]}
    """
    if isinstance(obj, torch.Tensor):
        obj = obj.detach().cpu().numpy()
    if isinstance(obj, np.ndarray | np.generic):
        obj = obj.tolist()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        return {to_jsonable(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, Sequence):
        return [to_jsonable(v) for v in obj]
    raise ValueError(
        f"cannot write {type(obj).__name__} to JSON; expected numbers, strings, "
        "lists, dicts, numpy arrays or tensors"
    )


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as strict JSON (indent 2) atomically; NaN/inf are written as ``null``.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_json(Path(d) / "r.json", {"recall": float("nan")}).read_text()
    '{\\n  "recall": null\\n}\\n'
    """
    text = json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n"
    return write_text(path, text)


def write_csv(
    path: str | os.PathLike, rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None
) -> Path:
    """Write dict rows as CSV atomically; NaN is written as ``nan``, a missing key as empty.

    Args:
        path: destination file.
        rows: one dict per line.
        columns: column order; default: every key in order of first appearance.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_csv(Path(d) / "r.csv", [{"a": 1, "b": float("nan")}, {"a": 2}]).read_text()
    'a,b\\n1,nan\\n2,\\n'
    """
    if columns is None:
        if not rows:
            raise ValueError("write_csv needs at least one row or explicit columns; received none")
        columns = list(dict.fromkeys(k for row in rows for k in row))

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: _csv_value(row.get(k)) for k in columns} for row in rows)
    return write_text(path, buffer.getvalue())


def _csv_value(value: Any) -> Any:
    if isinstance(value, torch.Tensor | np.ndarray | np.generic):
        return value.tolist()
    return value


def save_figure(fig: Figure, path: str | os.PathLike, dpi: float = 100) -> Path:
    """Save a matplotlib figure atomically; the format comes from the suffix (default PNG).

    The image is ``figsize * dpi`` pixels (no tight bounding box), and the figure stays open.

    >>> from matplotlib.figure import Figure
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     save_figure(Figure(figsize=(2, 1)), Path(d) / "f.png", dpi=10).read_bytes()[:4]
    b'\\x89PNG'
    """
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    buffer = io.BytesIO()
    # Render before opening the temp file so a drawing error leaves nothing behind.
    fig.savefig(buffer, format=fmt, dpi=dpi)
    return write_bytes(path, buffer.getvalue())


def render(fig: Figure, dpi: float = 100) -> np.ndarray:
    """Draw a figure into an (H, W, 3) uint8 RGB array (``figsize * dpi`` pixels).

    A figure drawn again (with new data) keeps its canvas, and with it the renderer's cache of
    text sizes. A figure marked by :func:`redraw_only` is drawn in full once; later calls paint
    only its changing artists over a copy of the rest.

    >>> from matplotlib.figure import Figure
    >>> render(Figure(figsize=(2, 1)), dpi=10).shape
    (10, 20, 3)
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    changing, background = getattr(fig, "_costseg_redraw", ((), None))
    if background is not None and background[0] == dpi:
        canvas.restore_region(background[1])
    else:
        fig.set_dpi(dpi)
        for artist in changing:
            artist.set_visible(False)
        canvas.draw()
        if changing:  # the unchanging rest, to paint the changing artists over next time
            fig._costseg_redraw = (changing, (dpi, canvas.copy_from_bbox(fig.bbox)))
        for artist in changing:
            artist.set_visible(True)
    for artist in changing:
        fig.draw_artist(artist)
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def redraw_only(fig: Figure, changing: Sequence) -> Figure:
    """Mark ``fig`` so that :func:`render` repaints only ``changing`` artists (drawn in this
    order, over everything else) after its first drawing: for a figure redrawn with new data
    whose layout, axes and text otherwise stay the same."""
    fig._costseg_redraw = (tuple(changing), None)
    return fig


def png_bytes(image: np.ndarray) -> bytes:
    """An (H, W) or (H, W, 3) uint8 array as PNG (fast compression: label maps and figures are
    mostly flat colour).

    >>> png_bytes(np.zeros((2, 3, 3), np.uint8))[:4]
    b'\\x89PNG'
    """
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an (H, W) or (H, W, 3) uint8 array as a PNG file atomically; return the path.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_png(Path(d) / "a.png", np.zeros((2, 3), np.uint8)).read_bytes()[:4]
    b'\\x89PNG'
    """
    return write_bytes(path, png_bytes(image))
