"""The ``evaluate.py`` job: options → plan (once) → one loop over the images → results.

:func:`plan` checks every option, opens the probability source
(:mod:`costseg.networks.sources`) and the data, builds the rule groups
(:mod:`costseg.rules`), splits off calibration images when a scaling or a guarantee needs
them, and claims a fresh output folder. :func:`run` fits and certifies on the calibration images
(:mod:`costseg.evaluation.held_out`), then passes over the reported images once: scores →
probabilities → every rule group → metrics (:mod:`costseg.metrics.scoring`, shared with
validation). :func:`evaluate` does both and hands the results to
:mod:`costseg.report.evaluation`. Under ``torchrun`` every process takes its own share of the
reported images and the metrics' sums are merged.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import Dataset

from costseg.calibration.scaling import Scaling
from costseg.classes import CLASS_NAMES, NUM_ROIS, class_indices
from costseg.data.from_config import build_dataset, eval_batch_size
from costseg.data.prior_maps import PriorMaps, heatmap_canvas
from costseg.evaluation.checks import (
    check_calibration_size,
    check_options,
    instance_classes,
    needs_priors,
    source_priors,
)
from costseg.evaluation.held_out import as_logits, certify, fit_scaling
from costseg.metrics import CalibrationError
from costseg.metrics.scoring import GroupMetrics, score_batch
from costseg.networks.sources import (
    Batch,
    Source,
    batches,
    open_source,
    resolve_device,
    with_mc_dropout,
)
from costseg.options import EvalOptions
from costseg.report.outputs import INCOMPLETE, BatchWriter, claim_output_dir, mark_complete
from costseg.report.results import EvalResults, Example, GroupResult
from costseg.rules import RuleGroup, named_group, temperature_group


@dataclass
class EvalPlan:
    """What one evaluation will do, decided once before the first image."""

    options: EvalOptions
    device: torch.device
    source: Source
    dataset: Dataset
    indices: list[int]  # this process's share of the reported images
    num_reported: int  # reported images over all processes
    calibration: tuple[Dataset, list[int]] | None  # images that fit / certify, never reported
    batch_size: int
    num_workers: int
    groups: list[RuleGroup]
    class_ids: list[int]
    output_dir: Path
    priors: PriorMaps
    canvas: tuple[int, int]
    instance_classes: tuple[list[int], str]  # classes of the instance metrics; what the outputs say


def plan(opts: EvalOptions) -> EvalPlan:
    """Check the options, open source and data, and claim the output folder."""
    groups = check_options(opts)
    device = resolve_device(opts.device)
    if _world_size() > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    source = open_source(opts.ckpt_path, opts.network, opts.probs, device)
    source = with_mc_dropout(source, opts.mc_dropout, opts.seed)
    if source.data_config is None and opts.data_root is None:
        raise ValueError(f"{source.description} names no dataset: pass --data_root")
    config = source.data_config or {}
    dataset = build_dataset(config, opts.split, opts.data_root)
    count = len(dataset) if opts.limit is None else min(opts.limit, len(dataset))
    if count == 0:
        raise ValueError(f"the {opts.split} split holds no images: nothing to evaluate")
    reported, calibration = _split_calibration(opts, config, dataset, count)
    if calibration is not None:
        candidates = next((g for g in groups if g.candidates), named_group(groups))
        check_calibration_size(opts, len(calibration[1]), len(candidates.names))
    base = _default_base(source)
    cache = (Path(opts.output_dir).resolve().parent if opts.output_dir else base.parent) / "priors"
    priors = PriorMaps(source_priors(source, opts, config, cache), CLASS_NAMES, device)
    if priors.priors is None and needs_priors(groups):
        raise ValueError("ml and --alpha_sweep need pixel-wise priors, and this source has none")
    return EvalPlan(
        options=opts,
        device=device,
        source=source,
        dataset=dataset,
        indices=reported[_rank() :: _world_size()],
        num_reported=len(reported),
        calibration=calibration,
        batch_size=opts.batch_size or eval_batch_size(config, opts.data_root),
        num_workers=int(config.get("init_args", {}).get("num_workers", 2)),
        groups=groups,
        class_ids=class_indices(opts.classes),
        priors=priors,
        canvas=heatmap_canvas(dataset),
        instance_classes=instance_classes(dataset, opts),
        output_dir=_on_rank0(lambda: claim_output_dir(opts.output_dir, opts.overwrite, base)),
    )


def run(plan: EvalPlan, after_batch: Callable[[list[Example]], None] | None = None) -> EvalResults:
    """Calibrate and certify on the held-out images, then one pass over the reported ones;
    ``after_batch(examples)`` after each of its batches (e.g. to start drawing figures)."""
    opts, extra = plan.options, {}
    scaling = Scaling()
    if opts.calibrate:
        scaling = fit_scaling(
            _calibration_batches(plan, "fit scaling"), opts.calibrate, plan.source.kind
        )
        print(f"calibration: {scaling.describe()}")
        extra["scaling"] = scaling.to_dict()
        if opts.temperature_sweep and scaling.kind == "temperature":
            named = named_group(plan.groups)
            plan.groups.append(temperature_group(named.rules, scaling.temperature))
    if opts.guarantee is not None:
        group = next(g for g in plan.groups if g.candidates)
        extra["certificate"] = certify(
            _calibration_batches(plan, "certify"),
            group,
            lambda b: _probabilities(plan, b, scaling),
            plan.priors.at,
            opts.target,
            opts.maximize,
            opts.guarantee,
            opts.guarantee_method,
            plan.class_ids,
        )
    return _report_pass(plan, scaling, extra, after_batch)


def _report_pass(plan: EvalPlan, scaling: Scaling, extra: dict, after_batch) -> EvalResults:
    opts, device = plan.options, plan.device
    classes, extra["instances"] = plan.instance_classes
    print(extra["instances"])
    metrics = [
        GroupMetrics(
            g,
            len(CLASS_NAMES),
            NUM_ROIS,
            None if g.temperature else plan.class_ids,
            plan.canvas,
            instance_classes=classes,
        ).to(device)
        for g in plan.groups
    ]
    ece = {"raw": CalibrationError(len(CLASS_NAMES)).to(device)}
    if scaling.kind != "none":
        ece["scaled"] = CalibrationError(len(CLASS_NAMES)).to(device)
    named = plan.groups.index(named_group(plan.groups))
    writer = BatchWriter(plan.output_dir, plan.groups[named].names, opts.save_predictions)
    examples: list[Example] = []
    desc = "evaluate" if opts.progress and _rank() == 0 else None
    with torch.inference_mode():
        for batch in batches(
            plan.source, plan.dataset, plan.indices, plan.batch_size, device, plan.num_workers, desc
        ):
            probs = _probabilities(plan, batch, scaling)
            if opts.save_probs:  # evaluate exactly what is saved, so --probs reproduces it
                probs = probs.half().float()
                writer.save_probs(batch.stems, probs)
            _update_ece(ece, plan, batch, probs)
            priors, roi = plan.priors.at(tuple(batch.labels.shape[-2:]))
            by_temperature = _tempered(plan, batch, probs)
            preds = [
                score_batch(
                    [g],
                    [m],
                    by_temperature[g.temperature],
                    batch.labels,
                    priors,
                    roi,
                    batch.instances,
                )[0]
                for g, m in zip(plan.groups, metrics, strict=True)
            ]
            writer.save_predictions(batch.stems, preds[named])
            _keep_examples(
                examples, opts.num_examples, batch, preds[named], opts.explorer and probs
            )
            if after_batch:
                after_batch(examples)
    extra["ece"] = {k: m.compute() for k, m in ece.items()}
    return EvalResults(
        output_dir=plan.output_dir,
        options=asdict(opts),
        source=plan.source.description,
        probabilities=_describe_probabilities(plan, scaling),
        class_ids=plan.class_ids,
        groups=[GroupResult(g, **m.compute()) for g, m in zip(plan.groups, metrics, strict=True)],
        examples=examples,
        roi=plan.priors.roi_map(),
        num_images=plan.num_reported,
        extra=extra,
    )


def evaluate(opts: EvalOptions) -> EvalResults:
    """Plan, run, and (on rank 0) write every output; returns the results.

    Figures known before the loop ends are drawn on forked processes meanwhile. The output
    folder is marked ``INCOMPLETE`` until every file is written; an interrupt or a failed write
    says where the partial outputs are."""
    planned, early = plan(opts), None
    out = planned.output_dir
    try:
        if _rank() == 0:
            from costseg.report.early_figures import EarlyFigures

            roi = planned.priors.roi_map()
            early = EarlyFigures(out, named_group(planned.groups), roi, opts.num_examples)
        results = run(planned, early.after_batch if early else None)
        if early:
            from costseg.report.evaluation import write_evaluation

            write_evaluation(results, early)
    except (KeyboardInterrupt, OSError) as err:
        if early:
            early.cancel()
        partial = f"the partial outputs in {out} are marked {INCOMPLETE}"
        if isinstance(err, KeyboardInterrupt):
            raise KeyboardInterrupt(partial) from None
        raise OSError(f"{err.strerror or err}: {err.filename or ''}; {partial}") from err
    except BaseException:
        if early:
            early.cancel()
        raise
    if _rank() == 0:
        mark_complete(out)
    return results


def _calibration_batches(plan: EvalPlan, what: str):
    dataset, indices = plan.calibration
    desc = f"{what} ({len(indices)} calibration images)" if plan.options.progress else None
    with torch.inference_mode():
        yield from batches(
            plan.source, dataset, indices, plan.batch_size, plan.device, plan.num_workers, desc
        )


def _probabilities(plan: EvalPlan, batch: Batch, scaling: Scaling) -> torch.Tensor:
    if scaling.kind != "none":
        return scaling.apply(as_logits(batch, plan.source.kind))
    return batch.scores if plan.source.kind == "probs" else batch.scores.softmax(1)


def _tempered(plan: EvalPlan, batch: Batch, probs: torch.Tensor) -> dict:
    """The probabilities of every temperature a group asks for (None: the main ones)."""
    out = {None: probs}
    for t in {g.temperature for g in plan.groups if g.temperature}:
        out[t] = Scaling("temperature", temperature=t).apply(as_logits(batch, plan.source.kind))
    return out


def _update_ece(ece: dict, plan: EvalPlan, batch: Batch, probs: torch.Tensor) -> None:
    if "scaled" in ece:
        ece["scaled"].update(probs, batch.labels)
        probs = _probabilities(plan, batch, Scaling())
    ece["raw"].update(probs, batch.labels)


def _describe_probabilities(plan: EvalPlan, scaling: Scaling) -> str:
    base = plan.source.probabilities  # saved ones, Monte-Carlo dropout, or None: the softmax
    if scaling.kind == "none" and base:
        text = f"{base}, no scaling"
    else:
        text = (f"{base}; " if base else "") + scaling.describe()
    return text + ("; rounded to float16 as saved" if plan.options.save_probs else "")


def _keep_examples(examples: list, limit: int, batch: Batch, preds: torch.Tensor, probs) -> None:
    """The first ``limit`` images; with ``probs`` (the explorer's), their float16 probabilities."""
    for i in range(min(len(batch.images), limit - len(examples))):
        kept = None if probs is False else probs[i].to("cpu", torch.float16)
        image, label = batch.images[i].cpu(), batch.labels[i].cpu()
        examples.append(Example(image, label, preds[i].cpu(), batch.stems[i], kept))


def _split_calibration(opts: EvalOptions, config: dict, dataset: Dataset, count: int):
    """(reported indices, calibration (dataset, indices) or None), disjoint by construction."""
    if not (opts.calibrate or opts.guarantee is not None):
        return list(range(count)), None
    if opts.calibration_split is not None:
        held = build_dataset(config, opts.calibration_split, opts.data_root)
        return list(range(count)), (held, list(range(len(held))))
    half = count // 2
    if half == 0:
        raise ValueError(f"{count} image(s): too few to split into calibration and report halves")
    return list(range(half, count)), (dataset, list(range(half)))


def _default_base(source: Source) -> Path:
    if source.run_dir is not None:
        return source.run_dir / "evaluation"
    name = str(next(iter(source.description.values()))).split(":")[-1].rstrip("/")
    return Path("eval") / (Path(name).stem or "network")


def _on_rank0(make):
    """``make()`` on rank 0, its value shared with every process (e.g. the output folder)."""
    value = [make() if _rank() == 0 else None]
    if dist.is_available() and dist.is_initialized():
        dist.broadcast_object_list(value, src=0)
    return value[0]


def _rank() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _world_size() -> int:
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size()
    return int(os.environ.get("WORLD_SIZE", "1"))
