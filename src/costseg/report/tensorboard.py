"""Send tables, figures, scalars and masks to TensorBoard.

Every helper takes a ``torch.utils.tensorboard.SummaryWriter``; under Lightning that is
``trainer.logger.experiment`` of a ``TensorBoardLogger``.

An evaluation reads in TensorBoard as in its folder (:mod:`costseg.report.evaluation`): its
tables as text, its figures as images, and scalars only where a value changes along something:
the sweeps, as curves over the grid index, α or T. One card per metric; the classes are runs
(``<output>/tensorboard/<class>``) overlaid in it, so the number of cards does not grow with
``--classes``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from matplotlib.figure import Figure

from costseg.report.figures import ArrayLike, masks_side_by_side
from costseg.workers import within

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter


STEPS = """Scalars are the sweeps' curves; the step is
* `sweep/*`, `alpha_sweep/*`: the rule's index (the row order of `sweep.csv`,
  `alpha_sweep.csv`; k for α = k · STEP),
* `temperature_sweep/*`: 100 · T (with a rule that defers, also its coverage,
  selective and handled recall in RoI 1 and its deferred share of the whole image),
* `defer_sweep/<rule>/*`: k for the rule's k-th defer cost (`defer_sweep.csv`): coverage,
  selective error and handled recall per RoI, the RoI's over all classes in this run.

Each class is a run (`tensorboard/<class>`); whole-image values (`*/miou`,
`*/deferred_rate`) are in this run."""


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
        preds: rule name → (H, W) train ids (255: deferred), in panel order.
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


@contextlib.contextmanager
def summary_writer(folder: Path) -> Iterator[SummaryWriter]:
    """A ``SummaryWriter`` of ``folder``, closed by :func:`close_writer` at the end."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(folder))
    try:
        yield writer
    finally:
        close_writer(writer)


def close_writer(writer: SummaryWriter) -> None:
    """Close ``writer`` once its events are on disk, waiting a bounded time for its writer
    thread (a hung file system ends in one line, :class:`costseg.workers.Stalled`)."""
    within(writer.close, f"TensorBoard's writer of {writer.log_dir}")
