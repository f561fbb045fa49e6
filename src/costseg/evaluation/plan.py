"""What one evaluation will do, decided once before the first image: the checked options, the
probability source, the data and its split into calibration and reported images, the rule
groups, the priors, and a claimed output folder. Under ``torchrun`` each process gets its own
share of the reported images."""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist
from torch.utils.data import Dataset

from costseg import workers
from costseg.classes import CLASS_NAMES, class_indices
from costseg.data.from_config import (
    StreetScenesSettings,
    build_dataset,
    data_settings,
    evaluated_data,
)
from costseg.data.prior_maps import PriorMaps, heatmap_canvas
from costseg.data.priors import note_priors
from costseg.evaluation.analyses import held_out_flags
from costseg.evaluation.checks import (
    check_calibration_size,
    check_options,
    instance_classes,
    source_priors,
)
from costseg.evaluation.processes import on_rank0, share, world_size
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import Source, resolve_device
from costseg.options import EvalOptions
from costseg.report.outputs import claim_output_dir
from costseg.rules import RuleGroup, named_group, require_priors

if TYPE_CHECKING:
    from costseg.data.shift import Shift


@dataclass
class EvalPlan:
    """What one evaluation will do, decided once before the first image."""

    options: EvalOptions
    device: torch.device
    source: Source
    dataset: Dataset  # the reported images (seen through the shift when there is one)
    indices: list[int]  # this process's share of the reported images
    positions: list[int]  # their positions among all reported images (the order of one process)
    num_reported: int  # reported images over all processes
    calibration: tuple[Dataset, list[int]] | None  # images that fit / certify, never reported
    meta_images: tuple[Dataset, list[int]] | None  # images that fit the meta models, never reported
    batch_size: int
    num_workers: int
    groups: list[RuleGroup]
    class_ids: list[int]
    output_dir: Path
    priors: PriorMaps
    canvas: tuple[int, int]
    instance_classes: tuple[list[int], str]  # classes of the instance metrics; what the outputs say
    shifts: list[Shift]  # --shift: with several, evaluation/shifts.py runs one evaluation each
    data: dict | None  # the images' data configuration (None: a dataset given in Python)
    held_out: dict = field(default_factory=dict)  # the held-out images, scored once (loop.py)


@dataclass
class Images:
    """The images of an evaluation: a named dataset (a data configuration: the source's, or
    Cityscapes at ``--data_root``), or a dataset given in Python (:func:`costseg.evaluate`)."""

    config: dict | None  # the data configuration; None for a dataset given in Python
    reported: Dataset  # the --split (with unknown objects for --anomalies)
    batch_size: int
    num_workers: int

    def split(self, name: str) -> Dataset:
        """Another split of the same data (--calibration_split, --meta_split)."""
        if self.config is None:
            raise ValueError(f"a dataset given in Python has no {name!r} split to hold out")
        return build_dataset(self.config, name)


def plan(
    opts: EvalOptions, source: Source | None = None, dataset: Dataset | None = None
) -> EvalPlan:
    """Check the options, open source and data, and claim the output folder; ``source`` and
    ``dataset`` replace the ones the options name (the Python API, :mod:`costseg.api`)."""
    groups = check_options(opts)
    shifts = _shifts(opts)
    device = resolve_device(opts.device)
    if world_size() > 1 and not dist.is_initialized():
        # a peer that stops answering ends each collective after STALL_SECONDS (evaluate())
        timeout = datetime.timedelta(seconds=workers.STALL_SECONDS)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timeout)
    if source is None:
        protocol = Protocol.from_options(opts)
        source = open_sources(
            opts.ckpt_path, opts.network, opts.probs, device, protocol, opts.mc_dropout, opts.seed
        )
    images = _named_images(opts, source) if dataset is None else Images(None, dataset, 1, 0)
    dataset = images.reported
    count = len(dataset) if opts.limit is None else min(opts.limit, len(dataset))
    if count == 0:
        raise ValueError(f"the {opts.split} split holds no images: nothing to evaluate")
    reported, calibration = _split_calibration(opts, images, count)
    meta_images = None
    if opts.meta or opts.fuse:
        meta_images = calibration
        if opts.meta_split is not None:
            held = images.split(opts.meta_split)
            meta_images = (held, list(range(min(opts.meta_images, len(held)))))
    if calibration is not None:
        candidates = next((g for g in groups if g.candidates), named_group(groups))
        check_calibration_size(opts, len(calibration[1]), candidates)
    batch_size = opts.batch_size or images.batch_size
    base = source.default_output("evaluation", "eval")
    cache = (Path(opts.output_dir).resolve().parent if opts.output_dir else base.parent) / "priors"
    geometric = opts.roi == "geometric"
    pixel_priors = source_priors(source, opts, images.config, cache)
    note_priors(source.description, opts.priors, dataset)
    priors = PriorMaps(pixel_priors, CLASS_NAMES, device, geometric)
    require_priors(groups, priors.priors)
    reported_images = dataset
    if len(shifts) == 1:
        from costseg.data.shift import ShiftedDataset

        reported_images = ShiftedDataset(dataset, shifts[0], opts.seed)
    return EvalPlan(
        options=opts,
        device=device,
        source=source,
        dataset=reported_images,
        indices=[reported[i] for i in share(len(reported))],
        positions=share(len(reported)),
        num_reported=len(reported),
        calibration=calibration,
        meta_images=meta_images,
        batch_size=batch_size,
        num_workers=min(images.num_workers, -(-count // batch_size)),  # no idle workers
        groups=groups,
        class_ids=class_indices(opts.classes),
        priors=priors,
        canvas=heatmap_canvas(dataset),
        instance_classes=instance_classes(dataset, opts),
        output_dir=on_rank0(lambda: claim_output_dir(opts.output_dir, opts.overwrite, base)),
        shifts=shifts,
        data=images.config,
    )


def _named_images(opts: EvalOptions, source: Source) -> Images:
    """The ``--split`` of the source's data or of Cityscapes at ``--data_root`` (the procedural
    scenes with unknown objects for --anomalies)."""
    if source.data_config is None and opts.data_root is None:
        raise ValueError(f"{source.description} names no dataset: pass --data_root")
    config = evaluated_data(source.data_config, opts.data_root)
    settings = data_settings(config)
    if not opts.anomalies:
        reported = build_dataset(config, opts.split)
    elif not isinstance(settings, StreetScenesSettings) or opts.data_root is not None:
        raise ValueError("--anomalies needs the procedural scenes: a network trained on them")
    else:
        reported = settings.dataset(opts.split, anomalies=True)
    return Images(config, reported, settings.eval_batch_size, settings.num_workers)


def _shifts(opts: EvalOptions) -> list[Shift]:
    """The parsed ``--shift`` values (albumentations is imported only when there are some)."""
    if not opts.shift:
        return []
    from costseg.data.shift import parse_shift

    return [parse_shift(text) for text in opts.shift]


def _split_calibration(opts: EvalOptions, images: Images, count: int):
    """(reported indices, calibration (dataset, indices) or None), disjoint by construction."""
    meta_held_out = (opts.meta or opts.fuse) and opts.meta_split is None
    if not (held_out_flags(opts) or meta_held_out):
        return list(range(count)), None
    if opts.calibration_split is not None:
        held = images.split(opts.calibration_split)
        return list(range(count)), (held, list(range(len(held))))
    half = count // 2
    if half == 0:
        raise ValueError(f"{count} image(s): too few to split into calibration and report halves")
    return list(range(half, count)), (images.reported, list(range(half)))
