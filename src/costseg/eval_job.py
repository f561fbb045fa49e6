"""The ``evaluate.py`` job: load a checkpoint, evaluate the rules (and sweeps), write results.

``cli.py`` parses the options into :class:`EvalOptions`; this module does the work.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist
from PIL import Image
from torch.utils.data import DataLoader

from costseg.checkpoints import check_classes, find_checkpoint
from costseg.classes import CLASS_NAMES, TRAIN_ID_TO_LABEL_ID, class_indices
from costseg.costs import barycentric_grid
from costseg.evaluation import RuleGroup, evaluate, result_rows, shard
from costseg.module import SegmentationModule
from costseg.rules import apply_rules, parse_rules
from costseg.sweep import (
    alpha_grid,
    alpha_group,
    parse_metric,
    parse_target,
    sweep_group,
    vertex_matrices,
)


@dataclass
class EvalOptions:
    """Everything ``evaluate.py`` can be told (see ``python evaluate.py --help``)."""

    cost: list[str] = field(default_factory=lambda: ["robotistic", "altruistic", "egoistic"])
    ckpt_path: str | None = None
    classes: list[str] = field(default_factory=lambda: ["person", "building"])
    output_dir: str | None = None
    split: str = "val"
    data_root: str | None = None
    limit: int | None = None
    batch_size: int | None = None
    device: str = "auto"
    save_predictions: bool = False
    num_examples: int = 3
    sweep: float | None = None
    vertices: list[str] = field(default_factory=lambda: ["robotistic", "altruistic", "egoistic"])
    vertex_scaling: str = "none"
    target: str | None = None
    maximize: str | None = None
    alpha_sweep: float | None = None
    alpha_cost: str | None = None
    progress: bool = True


def load_model(opts: EvalOptions) -> tuple[SegmentationModule, Path]:
    """The checkpoint's module on the chosen device, after checking its class list."""
    path = find_checkpoint(opts.ckpt_path)
    print(f"checkpoint: {path}")
    check_classes(path, CLASS_NAMES)
    device = opts.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    module = SegmentationModule.load_from_checkpoint(path, map_location=device)
    if module.data_config is None:
        raise ValueError(f"{path} holds no data configuration; pass a costseg checkpoint")
    return module, path


def make_loader(module: SegmentationModule, opts: EvalOptions) -> DataLoader:
    """The evaluation split of the checkpoint's dataset (with the command line's overrides)."""
    config = module.data_config
    module_name, _, class_name = config["class_path"].rpartition(".")
    init_args = dict(config["init_args"])
    if opts.data_root is not None:
        if "root" not in init_args:
            raise ValueError("--data_root applies to Cityscapes checkpoints only")
        init_args["root"] = opts.data_root
    data = getattr(importlib.import_module(module_name), class_name)(**init_args)
    if opts.split not in ("train", "val", "test"):
        raise ValueError(f"--split must be train, val or test, got {opts.split!r}")
    dataset = data.make_dataset(opts.split, augment=False)
    if opts.limit is not None:
        dataset = torch.utils.data.Subset(dataset, range(min(opts.limit, len(dataset))))
    batch = opts.batch_size or getattr(data, "eval_batch_size", 1)
    return DataLoader(shard(dataset), batch_size=batch, num_workers=data.num_workers)


def rule_groups(opts: EvalOptions, probs_classes: int) -> tuple[list[RuleGroup], dict]:
    """The named rules, and the sweeps asked for; plus what the report needs about them."""
    names = CLASS_NAMES[:probs_classes]
    rules = parse_rules(opts.cost, names)
    groups = [RuleGroup([r.name for r in rules], lambda p, pri: apply_rules(p, rules, pri))]
    info: dict = {"rules": rules}
    if opts.sweep is not None:
        vertices = vertex_matrices(opts.vertices, opts.vertex_scaling, names)
        weights = barycentric_grid(opts.sweep)
        groups.append(sweep_group(vertices, weights))
        info |= {"sweep": len(groups) - 1, "weights": weights, "vertices": vertices}
    if opts.alpha_sweep is not None:
        base = parse_rules([opts.alpha_cost], names)[0] if opts.alpha_cost else None
        label = base.name if base else "robotistic"
        alphas = alpha_grid(opts.alpha_sweep)
        groups.append(alpha_group(base.cost if base else None, alphas, label))
        info |= {"alpha": len(groups) - 1, "alphas": alphas, "alpha_label": label}
    return groups, info


def prediction_writer(out_dir: Path, names: list[str], loader: DataLoader):
    """A batch hook writing Cityscapes label-id PNGs per image and named rule."""
    dataset = loader.dataset
    stems = _image_stems(dataset)

    def write(index: int, images, labels, preds) -> None:
        first = index * loader.batch_size
        for i in range(len(images)):
            for k, name in enumerate(names):
                folder = out_dir / "predictions" / name
                folder.mkdir(parents=True, exist_ok=True)
                label_ids = TRAIN_ID_TO_LABEL_ID[preds[0][i, k].cpu().numpy()]
                Image.fromarray(label_ids).save(folder / f"{stems[first + i]}.png")

    return write


def _image_stems(dataset) -> list[str]:
    """``frankfurt_000000_000294`` style names (Cityscapes) or ``<split>_<index>`` (toy)."""
    indices = list(range(len(dataset)))
    while isinstance(dataset, torch.utils.data.Subset):
        indices = [dataset.indices[i] for i in indices]
        dataset = dataset.dataset
    files = getattr(dataset, "files", None)
    if files is not None:
        return [Path(files[i][0]).name.replace("_leftImg8bit.png", "") for i in indices]
    split = getattr(dataset, "split", "data")
    return [f"{split}_{i:06d}" for i in indices]


def run(opts: EvalOptions) -> dict:
    """Evaluate as ``opts`` says and write every output; returns the rows and results."""
    from costseg.report.evaluation import write_outputs

    _check_options(opts)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    module, ckpt = load_model(opts)
    class_ids = class_indices(opts.classes)
    loader = make_loader(module, opts)
    groups, info = rule_groups(opts, module.hparams.num_classes)
    out_dir = Path(opts.output_dir) if opts.output_dir else ckpt.parent.parent / "evaluation"
    examples: list = []

    def on_batch(index, images, labels, preds):
        if len(examples) < opts.num_examples:
            for i in range(min(len(images), opts.num_examples - len(examples))):
                examples.append((images[i].cpu(), labels[i].cpu(), preds[0][i].cpu()))
        if opts.save_predictions:
            save(index, images, labels, preds)

    save = prediction_writer(out_dir, groups[0].names, loader) if opts.save_predictions else None
    results = evaluate(module, loader, groups, class_ids, on_batch=on_batch, progress=opts.progress)
    rows = result_rows(groups[0].names, results[0], class_ids, CLASS_NAMES)
    if dist.is_initialized() and dist.get_rank() != 0:
        return {"rows": rows, "results": results}
    write_outputs(out_dir, opts, module, groups, results, rows, class_ids, info, examples)
    return {"rows": rows, "results": results, "output_dir": out_dir, "info": info}


def _check_options(opts: EvalOptions) -> None:
    """Fail on malformed options before any model is loaded."""
    class_indices(opts.classes)
    parse_rules(opts.cost)
    if opts.target or opts.maximize:
        if not (opts.target and opts.maximize and opts.sweep):
            raise ValueError("--target and --maximize go together, with --sweep STEP")
        parse_target(opts.target)
        parse_metric(opts.maximize)
    if opts.sweep is not None:
        vertex_matrices(opts.vertices, opts.vertex_scaling)
        barycentric_grid(opts.sweep)
    if opts.alpha_sweep is not None:
        alpha_grid(opts.alpha_sweep)
