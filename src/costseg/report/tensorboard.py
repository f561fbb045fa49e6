"""Send tables, figures, scalars and masks to TensorBoard.

Every helper takes a ``torch.utils.tensorboard.SummaryWriter``; under Lightning that is
``trainer.logger.experiment`` of a ``TensorBoardLogger``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

from matplotlib.figure import Figure

from costseg.report.figures import ArrayLike, masks_side_by_side

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter


def log_table(writer: SummaryWriter, tag: str, markdown: str, step: int = 0) -> None:
    """Log a Markdown table (e.g. :func:`costseg.report.tables.paper_table`) as text.

    >>> import tempfile
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     log_table(w, "eval/table", "| a |\\n|---|\\n| 1 |")
    """
    writer.add_text(tag, markdown, global_step=step)


def log_figures(writer: SummaryWriter, figures: Mapping[str, Figure], step: int = 0) -> None:
    """Render and log each figure under its tag, then close it.

    >>> import tempfile
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     log_figures(w, {"eval/empty": Figure(figsize=(1, 1))})
    """
    for tag, fig in figures.items():
        writer.add_figure(tag, fig, global_step=step, close=True)


def log_scalars(writer: SummaryWriter, scalars: Mapping[str, float], step: int = 0) -> list[str]:
    """Log each finite scalar under its tag; NaN and ±inf are NOT logged.

    TensorBoard cannot show an undefined ratio, so a NaN precision or recall is skipped
    rather than written as a number; the returned tags say which ones were left out (they stay
    visible as "nan" in the tables and as ``null`` in the JSON results).

    Returns:
        The tags that were skipped.

    >>> import tempfile
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     log_scalars(w, {"recall": 0.5, "precision": float("nan")})
    ['precision']
    """
    skipped = []
    for tag, value in scalars.items():
        value = float(value)
        if math.isfinite(value):
            writer.add_scalar(tag, value, global_step=step)
        else:
            skipped.append(tag)
    return skipped


def log_masks(
    writer: SummaryWriter,
    tag: str,
    image: ArrayLike,
    target: ArrayLike,
    preds: Mapping[str, ArrayLike],
    step: int = 0,
) -> None:
    """Log the image, the colourised ground truth and each rule's mask side by side.

    Args:
        writer: the SummaryWriter.
        tag: image tag.
        image: (H, W, 3) or (3, H, W) uint8.
        target: (H, W) train ids, 255 = ignore.
        preds: rule name → (H, W) train ids, in panel order.
        step: global step.

    >>> import tempfile, numpy as np
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     log_masks(w, "masks", np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2)), {})
    """
    strip = masks_side_by_side(image, target, preds)
    writer.add_image(tag, strip, global_step=step, dataformats="HWC")


def log_png(
    writer: SummaryWriter, tag: str, png: bytes, shape: tuple[int, ...], step: int = 0
) -> None:
    """Log an image already encoded as PNG, of ``shape`` (H, W, 3).

    ``SummaryWriter.add_image`` would convert, resample and encode the pixels again; this
    writes the same image record with the bytes as they are, through the writer's
    ``file_writer`` (so ``writer`` must be a ``torch.utils.tensorboard.SummaryWriter``).
    """
    from tensorboard.compat.proto.summary_pb2 import Summary

    height, width, channels = shape
    image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=png)
    writer.file_writer.add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)
