"""Pixel-wise priors (docs/definitions.md §3) from a folder of label maps, for ``--priors``.

    python scripts/count_priors.py LABELS --output priors.pt [--sigma PX] [--train_ids]

LABELS is searched recursively for Cityscapes label-id PNGs (``*_gtFine_labelIds.png``, mapped
to the 19 train ids); with ``--train_ids``, for PNGs that hold train ids already (0-18, 255 =
ignored). All labels must have one size; the priors are stored at it, smoothed with σ = 80 px per
1024 rows unless ``--sigma`` says otherwise, and the RoI map's share of each region is printed,
with a note when there are fewer than 50 labels (evaluate.py notes priors counted on the
evaluated images themselves).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from costseg.classes import CLASS_NAMES, LABEL_ID_TO_TRAIN_ID, ROI_NAMES
from costseg.cli import parse_options, user_errors
from costseg.data.cityscapes import LABEL_SUFFIX
from costseg.data.priors import default_sigma, pixel_priors, priors_note, roi_map, save_priors
from costseg.options import option
from costseg.values import number_above


@dataclass
class CountOptions:
    """What ``count_priors.py`` can be told (``--help``)."""

    labels: Path | None = option(
        help="folder searched recursively for label PNGs", type=Path, flag="LABELS"
    )
    output: Path | None = option(
        help="the priors file to write", type=Path, required=True, metavar="FILE"
    )
    sigma: float | None = option(
        help="smoothing in pixels, 0: none (default 80 per 1024 rows)",
        type=number_above(0, True, "a smoothing in pixels", "80"),
        metavar="PX",
    )
    train_ids: bool = option(False, "the PNGs hold train ids")
    overwrite: bool = option(False, "replace an existing --output")


def label_files(folder: Path, train_ids: bool) -> list[Path]:
    """The label PNGs under ``folder``, sorted; ValueError when there are none."""
    pattern = "*.png" if train_ids else f"*{LABEL_SUFFIX}"
    files = sorted(folder.rglob(pattern))
    if not files:
        raise ValueError(f"no {pattern} files under {folder}")
    return files


def read_train_ids(path: Path, train_ids: bool) -> torch.Tensor:
    """(H, W) int64 train ids of one label PNG (values are checked when counted)."""
    ids = np.asarray(Image.open(path))
    if ids.ndim != 2:
        raise ValueError(f"{path} should be a single-channel label PNG, got shape {ids.shape}")
    return torch.from_numpy((ids if train_ids else LABEL_ID_TO_TRAIN_ID[ids]).astype(np.int64))


def main(args: Sequence[str] | None = None) -> None:
    opts = parse_options(CountOptions, args, "count_priors.py", __doc__.splitlines()[0])
    with user_errors():
        if opts.output.exists() and not opts.overwrite:
            raise ValueError(f"{opts.output} exists: pass --overwrite to replace it")
        if not opts.labels.is_dir():
            raise ValueError(f"label folder not found: {opts.labels}")
        files = label_files(opts.labels, opts.train_ids)
        labels = (read_train_ids(f, opts.train_ids) for f in files)
        priors = pixel_priors(labels, len(CLASS_NAMES), opts.sigma)
        h, w = priors.shape[1:]
        count, sigma = len(files), default_sigma(h) if opts.sigma is None else opts.sigma
        settings = {"labels": str(opts.labels.resolve()), "num_labels": count, "sigma_px": sigma}
        note = priors_note(count)
        if note is not None:
            settings["note"] = note
        save_priors(opts.output, priors, CLASS_NAMES, settings=settings)
        roi = roi_map(priors)
        shares = ", ".join(
            f"{name} {float((roi == i).float().mean()):.0%}"
            for i, name in enumerate(ROI_NAMES)
            if i
        )
        print(
            f"{opts.output}: priors of {count} labels at {h} x {w}, σ = {sigma:g} px; RoIs {shares}"
        )
        if note is not None:
            print(note)


if __name__ == "__main__":
    sys.exit(main())
