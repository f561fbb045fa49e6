"""What one evaluation will do, decided once before the first image: each wanted analysis with
its settings, the probability source, the data and its split into calibration and reported
images, the rule groups, the priors, and a claimed output folder. Under ``torchrun`` each
process gets its own share of the reported images.

The options end here: everything below the plan (the loop, the analyses, the reports) reads the
plan and the analyses' settings (:mod:`costseg.evaluation.settings`), never the options."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as dist
from torch.utils.data import Dataset

from costseg import workers
from costseg.classes import CLASS_NAMES, INSTANCE_CLASSES, class_indices
from costseg.data.from_config import (
    StreetScenesSettings,
    build_dataset,
    data_settings,
    evaluated_data,
)
from costseg.data.prior_maps import PriorMaps, heatmap_canvas
from costseg.data.priors import note_priors
from costseg.evaluation.analyses import Entry, held_out_flags, wanted
from costseg.evaluation.checks import (
    check_calibration_size,
    check_design_size,
    check_groups,
    check_instance_targets,
    check_options,
    check_stream,
)
from costseg.evaluation.priors import evaluation_priors
from costseg.evaluation.processes import on_rank0, rank0_prints, share, world_size
from costseg.evaluation.settings import certified_choice, design_settings
from costseg.metrics.requirements import OBJECTIVES
from costseg.metrics.selection import Metric, parse_metric
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import Source, resolve_device
from costseg.options import EvalOptions
from costseg.report.certified import certificate_notes, certified_requirements
from costseg.report.outputs import claim_output_dir
from costseg.rules import (
    TEMPERATURES,
    RuleGroup,
    alpha_group,
    defer_costs,
    defer_group,
    grid_group,
    named_group,
    parse_rules,
    require_priors,
    require_roi,
    rules_group,
    temperature_group,
)

if TYPE_CHECKING:
    from costseg.data.shift import Shift


@dataclass(frozen=True)
class EvalPlan:
    """What one evaluation will do, decided once before the first image; never changed."""

    analyses: tuple[tuple[Entry, Any], ...]  # each wanted analysis with its settings
    record: dict  # the options as given, for results.json (a record: nothing reads it)
    device: torch.device
    source: Source
    description: dict  # the source's description, with the record of the priors used
    dataset: Dataset  # the reported images (seen through the shift when there is one)
    indices: list[int]  # this process's share of the reported images
    positions: list[int]  # their positions among all reported images (the order of one process)
    num_reported: int  # reported images over all processes
    calibration: tuple[Dataset, list[int]] | None  # images that fit / certify, never reported
    meta_images: tuple[Dataset, list[int]] | None  # images that fit the meta models, never reported
    batch_size: int
    num_workers: int
    groups: tuple[RuleGroup, ...]
    class_ids: list[int]  # --classes, then every other class a target or requirement names
    rois: tuple[int, ...]  # the RoIs a target or requirement names (shown beside the paper's)
    output_dir: Path
    priors: PriorMaps
    canvas: tuple[int, int]
    instance_classes: tuple[list[int], str]  # classes of the instance metrics; what the outputs say
    shifts: list[Shift]  # --shift: with several, evaluation/shifts.py runs one evaluation each
    data: dict | None  # the images' data configuration (None: a dataset given in Python)
    seed: int  # of the shifts' random corruptions
    shift_onset: int  # the index in ``dataset`` of the first image a shift changes
    num_examples: int  # the first reported images, whose examples are kept
    round_probs: bool  # the reported images' probabilities rounded to float16, as saved
    progress: bool  # progress lines


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
    opts: EvalOptions,
    source: Source | None = None,
    dataset: Dataset | None = None,
    groups: list[RuleGroup] | None = None,
) -> EvalPlan:
    """Check the options (unless ``groups``, their rule groups, were checked already), open
    source and data, and claim the output folder; ``source`` and ``dataset`` replace the ones
    the options name (the Python API, :mod:`costseg.api`)."""
    groups = checked_groups(opts) if groups is None else groups
    shifts = _shifts(opts)
    device = resolve_device(opts.device)
    if world_size() > 1 and not dist.is_initialized():
        # a peer that stops answering ends each collective after STALL_SECONDS (evaluate())
        timeout = datetime.timedelta(seconds=workers.STALL_SECONDS)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timeout)
    if source is None:
        protocol = Protocol.from_options(opts)
        with rank0_prints():
            source = open_sources(opts.ckpt_path, opts.network, opts.probs, device, protocol,
                                  opts.mc_dropout, opts.seed)  # fmt: skip
    images = _named_images(opts, source) if dataset is None else Images(None, dataset, 1, 0)
    dataset = images.reported
    count = len(dataset) if opts.limit is None else min(opts.limit, len(dataset))
    if count == 0:
        raise ValueError(f"the {opts.split} split holds no images: nothing to evaluate")
    reported, calibration = _split_calibration(opts, images, count)
    if opts.shift_onset is not None or opts.monitor_require:
        check_stream(
            opts.shift_onset, opts.monitor_delay if opts.monitor_require else 0, len(reported)
        )
    meta_images = None
    if opts.meta or opts.fuse:
        meta_images = calibration
        if opts.meta_split is not None:
            held = images.split(opts.meta_split)
            meta_images = (held, list(range(min(opts.meta_images, len(held)))))
    choice = certified_choice(opts)
    if calibration is not None and choice is not None:
        candidates = next((g for g in groups if g.candidates), named_group(groups))
        own_split = opts.calibration_split is not None
        check_calibration_size(choice, len(calibration[1]), candidates, own_split)
    designed = design_settings(opts)
    if calibration is not None and designed is not None:
        check_design_size(designed, len(calibration[1]), opts.calibration_split is not None)
    batch_size = opts.batch_size or images.batch_size
    base = source.default_output("evaluation", "eval")
    cache = (Path(opts.output_dir).resolve().parent if opts.output_dir else base.parent) / "priors"
    geometric = opts.roi == "geometric"
    with rank0_prints():
        pixel_priors, record = evaluation_priors(
            source, opts.priors, geometric, images.config, cache, opts.progress
        )
        description = _description(source, record)
        note_priors(description, opts.priors, dataset)
        for note in certificate_notes(opts.cost, description):
            print(note)
    priors = PriorMaps(pixel_priors, CLASS_NAMES, device, geometric)
    require_priors(groups, priors.priors)
    require_roi(
        groups, priors.roi_map(), "pass --priors FILE (a run's priors.pt) or --roi geometric"
    )
    measured, note = instance_classes(dataset, opts.classes)
    check_instance_targets(opts, measured, note)
    class_ids, named = class_indices(opts.classes), named_metrics(opts)
    reported_images = dataset
    onset = reported[0] + (opts.shift_onset or 0)  # the first shifted image's index
    if len(shifts) == 1:
        from costseg.data.shift import ShiftedDataset

        reported_images = ShiftedDataset(dataset, shifts[0], opts.seed, onset)
    return EvalPlan(
        analyses=tuple(wanted(opts)),
        record=dataclasses.asdict(opts),
        device=device,
        source=source,
        description=description,
        dataset=reported_images,
        indices=[reported[i] for i in share(len(reported))],
        positions=share(len(reported)),
        num_reported=len(reported),
        calibration=calibration,
        meta_images=meta_images,
        batch_size=batch_size,
        num_workers=min(images.num_workers, -(-count // batch_size)),  # no idle workers
        groups=tuple(groups),
        class_ids=list(dict.fromkeys([*class_ids, *(m.cls for m in named if m.cls is not None)])),
        rois=tuple(sorted({m.roi for m in named})),
        priors=priors,
        canvas=heatmap_canvas(dataset),
        instance_classes=(measured, note),
        output_dir=on_rank0(lambda: claim_output_dir(opts.output_dir, opts.overwrite, base)),
        shifts=shifts,
        data=images.config,
        seed=opts.seed,
        shift_onset=onset,
        num_examples=opts.num_examples,
        round_probs=opts.save_probs,
        progress=opts.progress,
    )


def named_metrics(opts: EvalOptions) -> list[Metric]:
    """The metrics ``--target``, ``--require``, the objectives (``miou`` and ``agreement`` name
    none) and the certificates of designed ``--cost`` files name."""
    texts = (*(opts.target or ()), *(opts.require or ()), opts.maximize, opts.design_maximize,
             opts.design_minimize)  # fmt: skip
    named = [parse_metric(re.split(r"[<>=]", t)[0]) for t in texts if t and t not in OBJECTIVES]
    for text in (t for cost in opts.cost for t in certified_requirements(cost)):
        with contextlib.suppress(ValueError):  # a header edited by hand names nothing
            named.append(parse_metric(re.split(r"[<>=]", text)[0]))
    return named


def checked_groups(opts: EvalOptions) -> list[RuleGroup]:
    """The rule groups ``opts`` ask for, every option checked (:mod:`costseg.evaluation.checks`)
    first: the checks of :func:`costseg.evaluate`, before a network moves or data is read."""
    check_options(opts)
    groups = rule_groups(opts)
    check_groups(opts, groups)
    return groups


def rule_groups(opts: EvalOptions) -> list[RuleGroup]:
    """The named rules (``--cost``) and every sweep's rule group, in the order the outputs show
    them; the first group with candidates is the one ``--target`` and ``--guarantee`` choose
    among."""
    rules = parse_rules(opts.cost, defer=opts.defer)  # the sweeps' rules never defer
    groups = [rules_group(rules)]
    if opts.defer_sweep is not None:
        groups.append(defer_group(opts.cost, defer_costs(*opts.defer_sweep)))
    if opts.sweep is not None:
        groups.append(grid_group(opts.vertices, opts.sweep, opts.vertex_scaling))
    if opts.alpha_sweep is not None:
        groups.append(alpha_group(opts.alpha_sweep, opts.alpha_cost))
    if opts.temperature_sweep:
        groups += [temperature_group(rules, t) for t in TEMPERATURES]
    if opts.fuse:
        from costseg.meta.fusion import fusion_group  # numba's segment passes: only with --fuse

        base, fused = parse_rules([opts.fuse_base])[0], parse_rules(opts.fuse)
        groups.append(fusion_group(base, fused, opts.fuse_tau, class_indices(opts.fuse_classes)))
    return groups


def instance_classes(dataset, classes: list[str]) -> tuple[list[int], str]:
    """The instance classes among ``classes`` whose misses are measured (none when the dataset
    has no instance ids), and a line saying so for the outputs."""
    chosen = [c for c in class_indices(classes) if c in INSTANCE_CLASSES]
    note = f"instance metrics for {', '.join(CLASS_NAMES[c] for c in chosen)} (definitions §9)"
    if not getattr(dataset, "has_instances", False):
        missing = getattr(dataset, "missing_instances", None)
        why = f"{missing} of {len(dataset)} images have" if missing else "the dataset has"
        chosen, note = [], f"instance metrics absent: {why} no instance ids (*_instanceIds.png)"
    elif not chosen:
        note = "instance metrics absent: no instance class among --classes"
    return chosen, note


def _description(source: Source, priors_record: Any) -> dict:
    """The source's description for the outputs, with the record of the priors the plan
    chose (a copy: the source's own is never changed)."""
    description = dict(source.description)
    if priors_record is not None:
        description["priors"] = priors_record
    elif isinstance(description.get("priors"), dict):
        description["priors"] = dict(description["priors"])
    return description


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
