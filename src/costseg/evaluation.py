"""The ``evaluate.py`` job: options → plan (once) → one loop over the images → results.

:func:`plan` checks every option, opens the probability source (:mod:`costseg.sources`) and the
data, builds the rule groups (:mod:`costseg.rules`) and claims a fresh output folder. :func:`run`
passes over the images once: scores → probabilities → every rule group → metrics (the step of
:mod:`costseg.scoring`, shared with validation). :func:`evaluate` does both and hands the
results to :mod:`costseg.report.evaluation`. Under ``torchrun`` every process takes its own
share of the images and the metrics' sums are merged.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from costseg.classes import CLASS_NAMES, class_indices
from costseg.data.from_config import build_dataset, eval_batch_size, image_stems
from costseg.data.prior_maps import PriorMaps, heatmap_canvas
from costseg.options import EvalOptions
from costseg.report.outputs import BatchWriter, claim_output_dir
from costseg.results import EvalResults, Example, GroupResult
from costseg.rules import RuleGroup, alpha_group, grid_group, parse_rules, rules_group
from costseg.scoring import GroupMetrics, score_batch
from costseg.selection import parse_metric, parse_target
from costseg.sources import Source, open_source, resolve_device


@dataclass
class EvalPlan:
    """What one evaluation will do, decided once before the first image."""

    options: EvalOptions
    device: torch.device
    source: Source
    dataset: Dataset
    indices: list[int]  # this process's share of the (limited) split
    batch_size: int
    groups: list[RuleGroup]
    class_ids: list[int]
    output_dir: Path
    priors: PriorMaps
    canvas: tuple[int, int]
    num_workers: int


def check_options(opts: EvalOptions) -> list[RuleGroup]:
    """Fail on malformed options before anything is loaded; returns the rule groups."""
    class_indices(opts.classes)
    if sum(x is not None for x in (opts.ckpt_path, opts.network, opts.probs)) > 1:
        raise ValueError("give at most one of --ckpt_path, --network and --probs")
    if opts.probs is not None and opts.data_root is None:
        raise ValueError("--probs needs --data_root: the dataset whose images were scored")
    if opts.save_probs and opts.probs is not None:
        raise ValueError("--save-probs writes a network's probabilities; with --probs they exist")
    groups = [rules_group(parse_rules(opts.cost))]
    if opts.target or opts.maximize:
        if not (opts.target and opts.maximize and opts.sweep):
            raise ValueError("--target and --maximize go together, with --sweep STEP")
        parse_target(opts.target)
        parse_metric(opts.maximize)
    if opts.sweep is not None:
        groups.append(grid_group(opts.vertices, opts.sweep, opts.vertex_scaling))
    if opts.alpha_sweep is not None:
        groups.append(alpha_group(opts.alpha_sweep, opts.alpha_cost))
    return groups


def plan(opts: EvalOptions) -> EvalPlan:
    """Check the options, open source and data, and claim the output folder."""
    groups = check_options(opts)
    device = resolve_device(opts.device)
    if _world_size() > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    source = open_source(opts.ckpt_path, opts.network, opts.probs, device)
    if source.data_config is None and opts.data_root is None:
        raise ValueError(f"{source.description} names no dataset: pass --data_root")
    config = source.data_config or {}
    dataset = build_dataset(config, opts.split, opts.data_root)
    count = len(dataset) if opts.limit is None else min(opts.limit, len(dataset))
    if count == 0:
        raise ValueError(f"the {opts.split} split holds no images: nothing to evaluate")
    rank, world = _rank(), _world_size()
    priors = PriorMaps(source.priors, CLASS_NAMES, device)
    if priors.priors is None and _needs_priors(groups):
        raise ValueError("ml and --alpha_sweep need pixel-wise priors, and this source has none")
    return EvalPlan(
        options=opts,
        device=device,
        source=source,
        dataset=dataset,
        indices=list(range(rank, count, world)),
        batch_size=opts.batch_size or eval_batch_size(config, opts.data_root),
        groups=groups,
        class_ids=class_indices(opts.classes),
        output_dir=_on_rank0(
            lambda: claim_output_dir(opts.output_dir, opts.overwrite, _default_base(source))
        ),
        priors=priors,
        canvas=heatmap_canvas(dataset),
        num_workers=int(config.get("init_args", {}).get("num_workers", 2)),
    )


def run(plan: EvalPlan) -> EvalResults:
    """One pass over the planned images: every rule group, all metrics, side outputs."""
    opts, device = plan.options, plan.device
    metrics = [
        GroupMetrics(g, len(CLASS_NAMES), 4, plan.class_ids, plan.canvas).to(device)
        for g in plan.groups
    ]
    writer = BatchWriter(plan.output_dir, plan.groups[0].names, opts.save_predictions)
    examples: list[Example] = []
    loader = DataLoader(
        _Indexed(plan.dataset, plan.indices),
        batch_size=plan.batch_size,
        num_workers=plan.num_workers,
        collate_fn=_collate_by_size,
    )
    with torch.inference_mode():
        for batch in tqdm(loader, "evaluate", disable=not opts.progress):
            for images, labels, indices in batch:
                images, labels = images.to(device), labels.to(device)
                stems = image_stems(plan.dataset, indices)
                probs = _probabilities(plan.source, images, stems)
                if opts.save_probs:  # evaluate exactly what is saved, so --probs reproduces it
                    probs = probs.half().float()
                    writer.save_probs(stems, probs)
                priors, roi = plan.priors.at(tuple(labels.shape[-2:]))
                preds = score_batch(plan.groups, metrics, probs, labels, priors, roi)
                writer.save_predictions(stems, preds[0])
                _keep_examples(examples, opts.num_examples, images, labels, preds[0])
    return EvalResults(
        output_dir=plan.output_dir,
        options=asdict(opts),
        source=plan.source.description,
        probabilities=_describe_probabilities(plan),
        class_ids=plan.class_ids,
        groups=[GroupResult(g, **m.compute()) for g, m in zip(plan.groups, metrics, strict=True)],
        examples=examples,
        roi=plan.priors.roi_map(),
        num_images=len(plan.indices) * _world_size(),
    )


def evaluate(opts: EvalOptions) -> EvalResults:
    """Plan, run, and (on rank 0) write every output; returns the results."""
    results = run(plan(opts))
    if _rank() == 0:
        from costseg.report.evaluation import write_evaluation

        write_evaluation(results)
    return results


def _probabilities(source: Source, images: torch.Tensor, stems: list[str]) -> torch.Tensor:
    scores = source.scores(images, stems)
    return scores if source.kind == "probs" else scores.softmax(1)


def _describe_probabilities(plan: EvalPlan) -> str:
    text = "saved probabilities" if plan.source.kind == "probs" else "softmax of the logits"
    return text + (" (rounded to float16, as saved)" if plan.options.save_probs else "")


def _keep_examples(examples, limit, images, labels, preds) -> None:
    for i in range(min(len(images), limit - len(examples))):
        examples.append(Example(images[i].cpu(), labels[i].cpu(), preds[i].cpu()))


def _needs_priors(groups: list[RuleGroup]) -> bool:
    return any(r.priors_alpha for r in groups[0].rules) or any(g.kind == "alpha" for g in groups)


def _default_base(source: Source) -> Path:
    if source.run_dir is not None:
        return source.run_dir / "evaluation"
    name = Path(str(next(iter(source.description.values())))).name.split(":")[-1]
    return Path("eval") / (Path(name).stem or "network")


class _Indexed(Dataset):
    """(image, label, index) of the chosen items of a dataset."""

    def __init__(self, dataset: Dataset, indices: list[int]) -> None:
        self.dataset, self.indices = dataset, indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        image, label = self.dataset[self.indices[i]]
        return image, label, self.indices[i]


def _collate_by_size(items) -> list[tuple[torch.Tensor, torch.Tensor, list[int]]]:
    """A batch as sub-batches of equal image size (datasets may mix resolutions)."""
    by_size: dict[tuple[int, ...], list] = {}
    for item in items:
        by_size.setdefault(tuple(item[1].shape), []).append(item)
    return [
        (torch.stack([i[0] for i in same]), torch.stack([i[1] for i in same]), [i[2] for i in same])
        for same in by_size.values()
    ]


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
    import os

    return int(os.environ.get("WORLD_SIZE", "1"))
