"""The ``predict.py`` job: check the inputs, open the source, then one pass over the images or
frames: network once → probabilities → every rule (one call) → files (docs/definitions.md §10).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from costseg.classes import CLASS_NAMES
from costseg.data.prior_maps import PriorMaps
from costseg.data.priors import check_priors_file, read_priors_file
from costseg.meta.collect import rule_segments
from costseg.meta.features import painted
from costseg.meta.models import SHOWN_MODEL, MetaModels, load_models
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import Source, resolve_device
from costseg.networks.uncertainty import output_maps
from costseg.options import PredictOptions, check_values
from costseg.prediction.inputs import Inputs, Item, find_inputs, read_image, video_frames
from costseg.prediction.outputs import PredictionWriter
from costseg.progress import progress
from costseg.report.explorer import ExplorerExample, embedded
from costseg.report.outputs import claim_output_dir, mark_complete
from costseg.rules import (
    Rule,
    apply_rules,
    parse_rules,
    require_priors,
    require_roi,
    rules_group,
    vertex_matrices,
)

Opener = Callable[[torch.device], Source]
"""Opens a source on a device: :func:`costseg.api.predict`'s module, once the job has checked."""


@dataclass
class PredictPlan:
    """What one prediction will do, decided before the first image."""

    options: PredictOptions
    inputs: Inputs
    device: torch.device
    source: Source
    rules: list[Rule]  # the --cost rules (with --defer: defer rows), then argmax if none is it
    output_dir: Path
    priors: PriorMaps
    meta_models: dict[str, MetaModels] | None = None  # rule → models (--meta_models)
    examples: list[ExplorerExample] = field(default_factory=list)

    @property
    def rule_names(self) -> list[str]:
        """The --cost rules' names."""
        return [r.name for r in self.rules[: len(self.options.cost)]]


def plan(opts: PredictOptions, source: Opener | None = None) -> PredictPlan:
    """Check the options (every value, as the command line's: the one check of every entry)
    and the inputs, claim the folder, then open the source: the options', or ``source``'s on
    the device (:func:`costseg.api.predict`'s module)."""
    check_values(opts)
    rules = parse_rules(opts.cost, defer=opts.defer)
    if opts.explorer:
        vertex_matrices(opts.vertices, opts.vertex_scaling)
    inputs = find_inputs(opts.input)
    check_priors_file(opts.priors)
    meta_models = _meta_models(opts.meta_models, rules) if opts.meta_models else None
    protocol = Protocol.from_options(opts)
    device = resolve_device(opts.device)
    claimed = claim_output_dir(opts.output_dir, opts.overwrite, Path()) if opts.output_dir else None
    if source is None:
        source = open_sources(
            opts.ckpt_path, opts.network, None, device, protocol, opts.mc_dropout, opts.seed
        )
    else:
        source = source(device)
    priors = source.priors
    if opts.priors is not None:
        priors = read_priors_file(opts.priors, CLASS_NAMES)["priors"]
    require_priors([rules_group(rules)], priors)
    maps = PriorMaps(priors, CLASS_NAMES, device, geometric=opts.roi == "geometric")
    require_roi([rules_group(rules)], maps.roi_map(), "pass --priors FILE or --roi geometric")
    if meta_models:
        _require_runs(meta_models, source)
    base = source.default_output("prediction", "predict")
    argmax = next((k for k, r in enumerate(rules) if _is_argmax(r)), None)
    if argmax is None:
        rules.append(Rule("argmax", None))
    return PredictPlan(
        options=opts,
        inputs=inputs,
        device=device,
        source=source,
        rules=rules,
        output_dir=claimed or claim_output_dir(None, False, base),
        priors=maps,
        meta_models=meta_models,
    )


def _meta_models(path: str, rules: list[Rule]) -> dict[str, MetaModels]:
    """The saved meta models of every --cost rule (their fitted :data:`SHOWN_MODEL`)."""
    models = load_models(path)
    missing = [
        r.name for r in rules if r.name not in models or SHOWN_MODEL not in models[r.name].fitted
    ]
    if missing:
        raise ValueError(
            f"--meta_models {path} holds no {SHOWN_MODEL} models of {', '.join(missing)} (it has "
            f"{', '.join(sorted(models)) or 'none'}); evaluate.py --meta with these --cost rules "
            "fits them"
        )
    return {r.name: models[r.name] for r in rules}


def _require_runs(models: dict[str, MetaModels], source: Source) -> None:
    """Models fitted with the mutual information MI need a source of several runs."""
    several = getattr(source.network, "average", None) is not None
    needing = [r for r, m in models.items() if any(f.startswith("MI") for f in m.features)]
    if needing and not several:
        raise ValueError(
            f"the meta models of {', '.join(needing)} read the mutual information MI: give a "
            "source of several runs (--mc_dropout or several --ckpt_path), as evaluate.py had"
        )


def _is_argmax(rule: Rule) -> bool:
    """Whether a rule decides as argmax: no priors, no defer row, and a symmetric matrix (one
    positive cost off the diagonal, 0 on it)."""
    if rule.priors_alpha or rule.defers or rule.regional:
        return False
    cost = rule.cost
    if cost is None:
        return True
    symmetric = cost[0, 1] * (1 - torch.eye(len(cost), dtype=cost.dtype))
    return bool(cost[0, 1] > 0 and (cost == symmetric).all())


def decide_image(
    plan: PredictPlan, image: np.ndarray, stem: str
) -> tuple[torch.Tensor, np.ndarray, object, dict[str, torch.Tensor], list[np.ndarray] | None]:
    """The network once (or as often as the protocol and the ensemble say), then every rule.

    Args:
        image: (H, W, 3) uint8 RGB.
        stem: the image's name (seeds Monte-Carlo dropout).

    Returns:
        probs (N, H, W) float32 (rounded to float16 with ``--save-probs``, so that the saved
        file reproduces the labels), maps (K + 1, H, W) uint8 train ids (the rules, then
        argmax; 255 where a rule defers), roi (H, W) int64 numpy or None, and the uncertainty
        maps (name → (H, W) float32 on the CPU, of the probabilities before the rounding),
        and with meta models per --cost rule the (H, W) predicted IoU of its segments (NaN off
        them), else None.
    """
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].to(plan.device)
    with torch.inference_mode():
        scores, expected_entropy = plan.source.scores_and_entropy(x, [stem])
        probs = plan.source.probabilities_of(scores)
        uncertainty = {k: v[0].cpu() for k, v in output_maps(probs, expected_entropy).items()}
        if plan.options.save_probs:
            probs = probs.half().float()
        priors, roi = plan.priors.at(image.shape[:2])
        maps = apply_rules(probs, plan.rules, priors, roi)[0]
    labels = maps.to(torch.uint8).cpu().numpy()
    segment_iou = None
    if plan.meta_models:
        segment_iou = [
            _predicted_iou(
                plan.meta_models[r.name], probs, labels[k], r, priors, expected_entropy, roi
            )
            for k, r in enumerate(plan.rules[: len(plan.rule_names)])
        ]
    return probs[0], labels, None if roi is None else roi.cpu().numpy(), uncertainty, segment_iou


def _predicted_iou(models: MetaModels, probs, labels, rule, priors, expected_entropy, roi):
    """(H, W) float64 predicted IoU of each segment of ``labels``, NaN off the segments."""
    table = rule_segments(probs, labels, rule, priors, expected_entropy, roi=roi)
    return painted(table.ids, models.predicted_iou(SHOWN_MODEL, table.columns))


def predict(opts: PredictOptions, source: Opener | None = None) -> Path:
    """Run ``predict.py`` (with ``source``'s source, opened on the device once every option is
    checked, in place of the one the options name); returns the output folder."""
    return run(plan(opts, source))


def run(job: PredictPlan) -> Path:
    """One pass over the planned images, then over each video's frames; returns the output
    folder."""
    opts = job.options
    k = len(job.rule_names)
    roi_record = _write_roi_map(job)
    writer = PredictionWriter(job.output_dir, job.rules[:k], opts.save_probs)
    argmax = next((i for i, r in enumerate(job.rules) if _is_argmax(r)), k)
    desc = "predict" if opts.progress else None
    images = job.inputs.images
    for item in progress(images, desc if images else None):
        image = read_image(item.path)
        probs, maps, roi, uncertainty, iou = decide_image(job, image, item.name)
        writer.image(item.name, image, maps[:k], maps[argmax], roi, probs, uncertainty, iou)
        _keep_example(job, item.name, image, probs, uncertainty)
    for item in job.inputs.videos:
        _run_video(job, writer, item, argmax, desc)
    if opts.explorer:
        _write_explorer(job)
    writer.finish(
        {
            "source": job.source.description,
            "input": [str(p) for p in job.inputs.paths],
            "roi_map": roi_record,
        }
    )
    mark_complete(job.output_dir)
    print(f"predictions written to {job.output_dir}")
    return job.output_dir


def _write_roi_map(job: PredictPlan) -> str:
    """``roi_map.png``, the RoI map the counts and the regional rules use (resized to each
    image), and what it is, for counts.json; said on the console for regional rules."""
    roi = job.priors.roi_map()
    if roi is None:
        return "none: no priors (counts over the whole image)"
    if job.options.roi == "geometric":
        record = "the geometric map of a street camera (docs/definitions.md §3)"
    else:
        given = job.options.priors
        record = f"the priors of {given}" if given else "the priors of the network's checkpoint"
        record = f"from {record} (docs/definitions.md §3)"
    from costseg.report.files import save_figure
    from costseg.report.priors import plot_roi_map  # matplotlib: only where a map is drawn

    save_figure(plot_roi_map(roi), job.output_dir / "roi_map.png")
    regional = [r.name for r in job.rules if r.regional]
    if regional:
        print(f"{', '.join(regional)}: each RoI decided with its own matrix; RoI map {record}, "
              f"drawn in {job.output_dir / 'roi_map.png'}")  # fmt: skip
    return record


def _run_video(
    job: PredictPlan, writer: PredictionWriter, item: Item, argmax: int, desc: str | None
) -> None:
    """One video, frame by frame: ``<name>_panels.mp4``, one overlay video per rule, counts."""
    k, video = len(job.rule_names), item.video
    writer.open_video(item.name, video.rate)
    try:
        frames = enumerate(video_frames(item.path))
        for i, image in progress(frames, desc and f"{desc} {item.name}", total=video.frames):
            stem = f"{item.name}_{i:06d}"
            probs, maps, roi, uncertainty, iou = decide_image(job, image, stem)
            writer.frame(stem, image, maps[:k], maps[argmax], roi, probs, uncertainty, iou)
            _keep_example(job, stem, image, probs, uncertainty)
    except BaseException:
        writer.close_videos(abandon=True)
        raise
    writer.close_videos()


def _keep_example(
    job: PredictPlan, stem: str, image: np.ndarray, probs: torch.Tensor, uncertainty: dict
) -> None:
    if job.options.explorer and len(job.examples) < job.options.num_examples:
        job.examples.append(embedded(stem, image, probs, uncertainty=uncertainty))


def _write_explorer(job: PredictPlan) -> None:
    from costseg.report.explorer import write_explorer
    from costseg.report.explorer_points import named_points

    opts = job.options
    vertices = vertex_matrices(opts.vertices, opts.vertex_scaling)
    source = job.source.description
    protocol = f"inference: {source.get('inference')}; test-time augmentation: {source.get('tta')}"
    write_explorer(
        job.output_dir / "explorer.html",
        job.examples,
        vertices,
        opts.vertices,
        named=named_points(job.rules[: len(opts.cost)], vertices, opts.vertex_scaling),
        defer=opts.defer,
        notes=[
            f"source: {source.get('network', '')}",
            protocol,
            f"uncertainty on hover: {source.get('uncertainty')}",
            "no labels: no metrics",
        ],
    )
