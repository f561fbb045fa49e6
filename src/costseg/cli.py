"""Command lines: ``python train.py`` and ``python evaluate.py``. Only this module parses arguments.

A user mistake ends with one line on stderr and exit status 2 (set ``COSTSEG_DEBUG=1`` for the
traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import torch
from lightning.pytorch import LightningDataModule, Trainer
from lightning.pytorch.cli import LightningCLI

from costseg.checkpoints import check_classes, find_checkpoint
from costseg.data.priors import pixel_priors, roi_map, save_priors
from costseg.eval_job import EvalOptions
from costseg.eval_job import run as run_evaluation
from costseg.module import SegmentationModule
from costseg.rules import RULE_NAMES

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn a user mistake (ValueError, FileNotFoundError) into one line and exit status 2."""
    try:
        yield
    except (ValueError, FileNotFoundError) as err:
        if os.environ.get("COSTSEG_DEBUG"):
            raise
        # Errors raised in a DataLoader worker carry its traceback: keep the original last line.
        lines = str(err).strip().splitlines() or [err.__class__.__name__]
        print(f"error: {lines[-1]}", file=sys.stderr)
        sys.exit(2)


class TrainCLI(LightningCLI):
    """LightningCLI with ``--ckpt_path`` to resume (``last`` = the newest ``runs/**/last.ckpt``)."""

    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument(
            "--ckpt_path",
            type=str | None,
            default=None,
            help="resume training from this checkpoint ('last': newest runs/**/last.ckpt)",
        )


def train_main(args: Sequence[str] | None = None) -> tuple[SegmentationModule, Trainer]:
    """``python train.py [--config configs/toy.yaml] [--trainer.max_steps 100] ...``.

    Returns:
        the trained module and its trainer (for scripts and tests).
    """
    args = list(sys.argv[1:] if args is None else args)
    if not any(a == "--config" or a.startswith("--config=") for a in args):
        args = ["--config", str(CONFIG_DIR / "toy.yaml"), *args]
    with user_errors():
        cli = TrainCLI(
            SegmentationModule,
            LightningDataModule,
            subclass_mode_data=True,
            run=False,
            args=args,
            save_config_kwargs={"overwrite": True},
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


def _data_config(cli: LightningCLI) -> dict:
    data = cli.config["data"]
    return {"class_path": data["class_path"], "init_args": dict(data.get("init_args", {}))}


def _compute_priors(model: SegmentationModule, data, trainer) -> torch.Tensor:
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


def evaluate_parser() -> argparse.ArgumentParser:
    """The options of ``evaluate.py``; defaults are those of :class:`EvalOptions`."""
    d = EvalOptions()
    p = argparse.ArgumentParser(
        prog="evaluate.py",
        description="Evaluate a checkpoint under cost-based decision rules: per-class precision "
        "and recall in regions of interest, FP/FN segments, mIoU; tables, figures, JSON, "
        "TensorBoard; optionally a sweep over the value-space triangle.",
    )
    add = p.add_argument
    add("--cost", nargs="+", default=d.cost, help=f"rules: {', '.join(RULE_NAMES)} or a .yaml")
    add("--ckpt_path", default=None, help="checkpoint (default: newest runs/**/last.ckpt)")
    add("--classes", nargs="+", default=d.classes, help="classes of the table and segment maps")
    add("--output_dir", default=None, help="default: <run folder>/evaluation")
    add("--split", default=d.split, choices=("train", "val", "test"))
    add("--data_root", default=None, help="Cityscapes root, if not the one trained with")
    add("--limit", type=int, default=None, help="evaluate only the first N images")
    add("--batch_size", type=int, default=None)
    add("--device", default=d.device, help="auto, cpu, cuda, cuda:1, ...")
    add(
        "--save-predictions",
        dest="save_predictions",
        action="store_true",
        help="write Cityscapes label-id PNGs per image and rule",
    )
    add("--num_examples", type=int, default=d.num_examples, help="images in the mask figures")
    add(
        "--sweep",
        type=float,
        default=None,
        metavar="STEP",
        help="also sweep the barycentric grid of this step over the three --vertices",
    )
    add("--vertices", nargs=3, default=d.vertices, help="the triangle's corners")
    add(
        "--vertex_scaling",
        default=d.vertex_scaling,
        choices=("none", "mean"),
        help="'mean': rescale each vertex to unit mean off-diagonal cost before mixing",
    )
    add("--target", default=None, help="constraint on the sweep, e.g. 'person:roi1:recall>=0.99'")
    add(
        "--maximize",
        default=None,
        help="what to maximise under --target, e.g. person:roi1:precision",
    )
    add(
        "--alpha_sweep",
        type=float,
        default=None,
        metavar="STEP",
        help="also sweep the prior-adapted rule from Bayes (α=0) to ML (α=1)",
    )
    add("--alpha_cost", default=None, help="cost matrix of the α sweep (default: symmetric)")
    add("--no-progress", dest="progress", action="store_false")
    return p


def evaluate_main(args: Sequence[str] | None = None) -> None:
    """``python evaluate.py --cost egoistic`` (see ``--help``)."""
    opts = EvalOptions(**vars(evaluate_parser().parse_args(args)))
    with user_errors():
        run_evaluation(opts)
