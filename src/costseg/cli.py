"""Command lines: ``python train.py`` and ``python evaluate.py``. Only this module parses arguments.

A user mistake ends with one line on stderr and exit status 2 (set ``COSTSEG_DEBUG=1`` for the
traceback). Heavy libraries (torch, Lightning) are imported only once they are needed, so
``--help`` answers at once.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from costseg.options import EvalOptions

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
COST_CHOICES = "robotistic, altruistic, egoistic, ml or a .yaml cost file"


def fail(message: str, join: bool = False) -> NoReturn:
    """Print one line ``error: message`` on stderr and exit with status 2.

    Of a multi-line message the last line is kept (an error raised in a DataLoader worker
    carries the worker's traceback before it), or, with ``join``, all lines joined.
    """
    lines = [line.strip() for line in str(message).strip().splitlines()] or ["unknown error"]
    print(f"error: {' '.join(lines) if join else lines[-1]}", file=sys.stderr)
    sys.exit(2)


@contextlib.contextmanager
def user_errors(*extra: type[BaseException]) -> Iterator[None]:
    """Turn a user mistake (ValueError, OSError and ``extra``) into one line and exit status 2."""
    try:
        yield
    except (ValueError, OSError, *extra) as err:
        if os.environ.get("COSTSEG_DEBUG"):
            raise
        fail(str(err) or err.__class__.__name__, isinstance(err, argparse.ArgumentError))


def train_main(args: Sequence[str] | None = None) -> tuple[Any, Any]:
    """``python train.py [--config configs/toy.yaml] [--trainer.max_steps 100] ...``.

    Returns:
        the trained module and its trainer (for scripts and tests).
    """
    args = list(sys.argv[1:] if args is None else args)
    if not any(a == "--config" or a.startswith("--config=") for a in args):
        args = ["--config", str(CONFIG_DIR / "toy.yaml"), *args]
    if "-h" in args or "--help" in args:
        print_train_help(args)
        sys.exit(0)
    if "--help_all" in args:  # LightningCLI's own help: every option of every class (slow)
        args[args.index("--help_all")] = "--help"
    from jsonargparse import ArgumentError
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from costseg.training import run_training

    with user_errors(ArgumentError, MisconfigurationException, ImportError):
        return run_training(args)


def print_train_help(args: Sequence[str]) -> None:
    """A fast ``train.py --help``: usage and every key of the chosen config with its value.

    LightningCLI's own help needs Lightning imported (~10 s on 2 cores): ``--help_all``.
    """
    import yaml

    path = Path(
        args[args.index("--config") + 1]
        if "--config" in args
        else next(a.split("=", 1)[1] for a in args if a.startswith("--config="))
    )
    print(
        "usage: train.py [--config FILE] [--KEY VALUE ...] [--ckpt_path PATH|last] "
        "[--print_config] [--help_all]\n\n"
        "Train DeepLabv3+ with LightningCLI. Every key of the config can be overridden, e.g.\n"
        "  python train.py --trainer.max_steps 3000 --model.backbone resnet34\n"
        "  python train.py --config configs/cityscapes.yaml --data.init_args.root DIR\n"
        "  python train.py --ckpt_path last        # resume the newest runs/**/last.ckpt\n"
        "--help_all lists every option of the trainer, model and data classes.\n\n"
        f"Keys of {path} and their values:"
    )
    try:
        config = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        fail(f"cannot read --config {path}: {err}")
    for key, value in _flatten(config):
        print(f"  --{key} {value}")


def _flatten(config: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(config, dict):
        for key, value in config.items():
            yield from _flatten(value, f"{prefix}{key}.")
    else:
        yield prefix.rstrip("."), config


class OneLineParser(argparse.ArgumentParser):
    """argparse, with every parsing error as one line on stderr (exit status 2)."""

    def error(self, message: str) -> NoReturn:
        fail(f"{self.prog}: {message}")


def whole_number(minimum: int):
    """argparse type: an integer >= ``minimum``.

    >>> whole_number(1)("3"), whole_number(0).__name__
    (3, 'integer >= 0')
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            shown = repr(text) if value is None else value
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {shown}")
        return value

    parse.__name__ = f"integer >= {minimum}"
    return parse


def step_size(text: str) -> float:
    """argparse type: a grid step 1/n in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a step such as 0.1, got {text!r}") from None
    n = round(1 / value) if 0 < value <= 1 else 0
    if n < 1 or abs(n * value - 1) > 1e-9:
        raise argparse.ArgumentTypeError(f"expected a step 1/n in (0, 1], e.g. 0.1, got {text}")
    return value


def evaluate_parser() -> argparse.ArgumentParser:
    """The options of ``evaluate.py``; defaults are those of :class:`EvalOptions`."""
    d = EvalOptions()
    p = OneLineParser(
        prog="evaluate.py",
        description="Evaluate a network under cost-based decision rules: per-class precision "
        "and recall in regions of interest, FP/FN segments, mIoU; tables, figures, JSON, "
        "TensorBoard; optionally sweeps over the value-space triangle and the α path.",
    )
    add = p.add_argument
    add("--cost", nargs="+", default=d.cost, help=f"rules: {COST_CHOICES}")
    src = p.add_argument_group("probability source (one of; default: newest runs/**/last.ckpt)")
    src.add_argument("--ckpt_path", help="a costseg checkpoint")
    src.add_argument("--network", help="costseg:PATH, vainf:PATH, hf:DIR (alias segformer:DIR)")
    src.add_argument("--probs", help="folder of saved probabilities (<image>.npz or .pt)")
    src.add_argument(
        "--mc_dropout",
        type=whole_number(1),
        metavar="N",
        help="Monte-Carlo dropout: mean softmax of N passes with dropout active",
    )
    src.add_argument("--seed", type=whole_number(0), default=d.seed, help="seed of --mc_dropout")
    add("--data_root", help="Cityscapes root (needed for --network/--probs of other networks)")
    add("--split", default=d.split, choices=("train", "val", "test"))
    add("--classes", nargs="+", default=d.classes, help="classes of the table and segment maps")
    add("--output_dir", help="default: a new <run>/evaluation/version_<n>")
    add("--overwrite", action="store_true", help="allow an --output_dir that holds results")
    add("--limit", type=whole_number(1), help="evaluate only the first N images")
    add("--batch_size", type=whole_number(1))
    add("--device", default=d.device, help="auto, cpu, cuda, cuda:1, ...")
    add(
        "--save-predictions",
        dest="save_predictions",
        action="store_true",
        help="write Cityscapes label-id PNGs per image and rule",
    )
    add(
        "--save-probs",
        dest="save_probs",
        action="store_true",
        help="write each image's probabilities (float16 .npz) for later --probs runs",
    )
    add(
        "--num_examples",
        type=whole_number(0),
        default=d.num_examples,
        help="images in the mask figures",
    )
    add(
        "--sweep",
        type=step_size,
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
    add("--target", help="constraint on the sweep, e.g. 'person:roi1:recall>=0.99'")
    add("--maximize", help="what to maximise under --target, e.g. person:roi1:precision")
    add(
        "--alpha_sweep",
        type=step_size,
        metavar="STEP",
        help="also sweep the prior-adapted rule from Bayes (α=0) to ML (α=1)",
    )
    add("--alpha_cost", help="cost matrix of the α sweep (default: symmetric)")
    cal = p.add_argument_group("calibration and guarantees (fitted on held-out images)")
    cal.add_argument(
        "--calibrate",
        choices=("temperature", "vector"),
        help="scale the logits, fitted on the first half of the split (or --calibration_split); "
        "the second half is reported",
    )
    cal.add_argument(
        "--calibration_split",
        choices=("train", "val", "test"),
        help="fit / certify on this split instead of the first half of --split",
    )
    cal.add_argument(
        "--temperature_sweep",
        action="store_true",
        help="every named rule at T = 0.5 ... 2 (and the fitted T), the network run once",
    )
    cal.add_argument(
        "--guarantee",
        type=float,
        metavar="DELTA",
        help="choose the --sweep / --alpha_sweep point with P(risk > α) <= DELTA "
        "(Learn-then-Test); α comes from --target",
    )
    cal.add_argument(
        "--guarantee_method",
        default=d.guarantee_method,
        choices=("bonferroni", "fixed_sequence"),
        help="family-wise error control (fixed_sequence tests along the grid / α order)",
    )
    add("--no-progress", dest="progress", action="store_false")
    return p


def evaluate_main(args: Sequence[str] | None = None) -> Any:
    """``python evaluate.py --cost egoistic`` (see ``--help``); returns the results."""
    opts = EvalOptions(**vars(evaluate_parser().parse_args(args)))
    with user_errors():
        from costseg.evaluation import evaluate

        return evaluate(opts)
