"""Atomic writers for result files: text, JSON, CSV and figures.

Every writer creates the parent folders, writes to a temporary file in the destination folder
and renames it over the destination (``os.replace``), so a reader never sees a half-written
file, even if the process is killed mid-write.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn, not with the writers
    from matplotlib.figure import Figure


def _atomic_write(path: str | os.PathLike, data: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with open(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path.

    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_text(Path(d) / "a" / "b.txt", "hi").read_text()
    'hi'
    """
    return _atomic_write(path, text.encode("utf-8"))


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
    >>> with tempfile.TemporaryDirectory() as d:
    ...     save_figure(Figure(figsize=(2, 1)), Path(d) / "f.png", dpi=10).read_bytes()[:4]
    b'\\x89PNG'
    """
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    buffer = io.BytesIO()
    # Render before opening the temp file so a drawing error leaves nothing behind.
    fig.savefig(buffer, format=fmt, dpi=dpi)
    return _atomic_write(path, buffer.getvalue())


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
    """An (H, W, 3) uint8 array as PNG (fast compression: figures are mostly flat colour).

    >>> png = png_bytes(np.zeros((2, 3, 3), np.uint8))
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_bytes(Path(d) / "a.png", png).read_bytes()[:4]
    b'\\x89PNG'
    """
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    return _atomic_write(path, data)
