"""``train.py``: LightningCLI wiring, priors before the first step, resuming.

:func:`costseg.cli.train_main` calls :func:`run_training` once Lightning is needed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch import LightningDataModule, Trainer
from lightning.pytorch.cli import LightningCLI

from costseg.checkpoints import check_classes, find_checkpoint
from costseg.data.priors import pixel_priors, roi_map, save_priors
from costseg.module import SegmentationModule


class TrainCLI(LightningCLI):
    """LightningCLI with ``--ckpt_path`` to resume (``last`` = the newest ``runs/**/last.ckpt``)."""

    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument(
            "--ckpt_path",
            type=str | None,
            default=None,
            help="resume training from this checkpoint ('last': newest runs/**/last.ckpt)",
        )


def run_training(args: Sequence[str]) -> tuple[SegmentationModule, Trainer]:
    """Parse ``args`` (a config and overrides), compute priors or resume, and fit."""
    cli = TrainCLI(
        SegmentationModule,
        LightningDataModule,
        subclass_mode_data=True,
        run=False,
        args=list(args),
        save_config_kwargs={"overwrite": True},
        parser_kwargs={"exit_on_error": False},
    )
    model, data, trainer = cli.model, cli.datamodule, cli.trainer
    if model.hparams.num_classes != data.num_classes:
        raise ValueError(
            f"model.num_classes is {model.hparams.num_classes} but the dataset has "
            f"{data.num_classes} classes"
        )
    model.data_config = _data_config(cli)
    ckpt_path = cli.config.get("ckpt_path")
    if ckpt_path:
        ckpt_path = str(find_checkpoint(ckpt_path))
        check_classes(ckpt_path, data.class_names)
        print(f"resuming from {ckpt_path}")
    else:
        model.priors = _compute_priors(model, data, trainer)
    trainer.fit(model, data, ckpt_path=ckpt_path)
    if trainer.checkpoint_callback is not None:
        print(f"checkpoints: {trainer.checkpoint_callback.dirpath}")
    return model, trainer


def _data_config(cli: LightningCLI) -> dict[str, Any]:
    data = cli.config["data"]
    return {"class_path": data["class_path"], "init_args": dict(data.get("init_args", {}))}


def _compute_priors(model: SegmentationModule, data, trainer: Trainer) -> torch.Tensor:
    """Pixel-wise priors from the training labels, saved (with figures) in the run folder."""
    from costseg.report.figures import plot_priors, plot_roi_map
    from costseg.report.files import save_figure

    priors = pixel_priors(
        data.prior_labels(), data.num_classes, sigma=model.hparams.prior_sigma, progress=True
    )
    if trainer.is_global_zero and trainer.log_dir:
        run = Path(trainer.log_dir)
        save_priors(run / "priors.pt", priors, data.class_names)
        save_figure(plot_priors(priors, data.class_names), run / "priors.png")
        save_figure(plot_roi_map(roi_map(priors, data.class_names)), run / "roi_map.png")
    return priors
