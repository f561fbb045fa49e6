"""``scripts/export.py``: one network and the decision of §1 as an ONNX graph with a sidecar JSON
(``docs/definitions.md §19``, ``docs/deploy.md``).

The options are checked (one source, no Monte-Carlo dropout, outputs free or ``--overwrite``)
before the network loads. The graph is traced with torch's TorchScript-based exporter (dynamic
batch, height, width and matrix rows; with ``--regional`` the stack's matrices and the RoI map's
size too), run once by onnxruntime at a size other than the traced one and compared with the
reference decision on PyTorch's probabilities, and only then written.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from costseg.atomic import AtomicFile
from costseg.classes import CLASS_NAMES, NUM_CLASSES
from costseg.costs import COSTS_DIR, PRESETS, load_cost, symmetric_cost
from costseg.data.priors import geometric_roi_map, save_priors
from costseg.export.graph import INPUTS, OUTPUTS, REGIONAL_INPUTS, DecisionGraph, graph_roi
from costseg.export.parity import Parity, parity
from costseg.networks.onnx import GRAPH_METADATA
from costseg.options import ExportOptions

__all__ = ["ExportPlan", "Exported", "export", "plan_export", "sample_inputs", "trace_graph"]

TRACE_SIZE = (64, 96)
"""(H, W) of the images the graph is traced with."""
CHECK_SIZE = (72, 136)
"""(H, W) of the check after tracing: another size, not a multiple of 16."""
OPSET = 17


@dataclass(frozen=True)
class ExportPlan:
    """What to export where: the ``--ckpt_path`` (or ``costseg:``) checkpoint or another
    ``--network`` spec, the graph, its sidecar JSON and (for a costseg checkpoint with
    priors) the priors file, in the format ``--priors`` reads (a run's ``priors.pt``)."""

    ckpt_path: str | None
    network: str | None
    output: Path
    probabilities: bool
    regional: bool = False

    @property
    def sidecar(self) -> Path:
        return self.output.with_suffix(".json")

    @property
    def priors_file(self) -> Path:
        return self.output.with_suffix(".priors.pt")


@dataclass(frozen=True)
class Exported:
    """What :func:`export` wrote, and the check of the graph before it was written."""

    graph: Path
    sidecar: Path
    priors_file: Path | None
    """The checkpoint's pixel-wise priors (None: a source without priors)."""
    parity: Parity
    """The graph's labels against the reference at ``CHECK_SIZE`` (docs/definitions.md §19)."""


def plan_export(opts: ExportOptions) -> ExportPlan:
    """Check the options before anything loads; ValueError or FileNotFoundError in one line.

    >>> plan_export(ExportOptions(ckpt_path=["a.ckpt", "b.ckpt"], output="m.onnx"))
    Traceback (most recent call last):
    ...
    ValueError: an ensemble (2 sources) has no single graph: export one network at a time
    """
    from costseg.checkpoints import find_checkpoint
    from costseg.networks import check_spec

    ckpt_path, network, output = opts.ckpt_path, opts.network, str(opts.output)
    sources = [*(ckpt_path or []), *(network or [])]
    if len(sources) > 1:
        raise ValueError(
            f"an ensemble ({len(sources)} sources) has no single graph: "
            "export one network at a time"
        )
    if opts.mc_dropout is not None:
        raise ValueError(
            "Monte-Carlo dropout has no single graph (its passes are random): export without "
            "--mc_dropout"
        )
    spec = network[0] if network else None
    if spec is not None and spec.startswith("onnx:"):
        raise ValueError(f"{spec} is an ONNX file already: export a PyTorch network")
    plan = ExportPlan(
        ckpt_path[0] if ckpt_path else None, spec, Path(output), opts.probabilities, opts.regional
    )
    if plan.output.suffix != ".onnx":
        raise ValueError(f"--output {output} should end in .onnx")
    for path in (plan.output, plan.sidecar, plan.priors_file):
        if path.exists() and not opts.overwrite:
            raise ValueError(f"{path} exists: choose another --output or add --overwrite")
    if spec is not None and not spec.startswith("costseg:"):
        check_spec(spec)
    else:
        find_checkpoint(spec.removeprefix("costseg:") if spec else plan.ckpt_path)
    return plan


def export(plan: ExportPlan) -> Exported:
    """Load the network, trace and check its graph, write the graph, the sidecar and the priors.

    Returns:
        the files written and the graph's check.
    """
    network, priors, source = _load(plan)
    graph = DecisionGraph(network, probabilities=True, regional=plan.regional)
    model = trace_graph(graph)
    checked, result = _check(graph, model)
    if not plan.probabilities:  # the probabilities stay inside; only the output goes
        del model.graph.output[OUTPUTS.index("probabilities")]
    sidecar = _sidecar(plan, network, source, priors is not None, checked)
    model.metadata_props.add(key=GRAPH_METADATA, value=json.dumps(sidecar))
    import onnx

    with AtomicFile(plan.output) as tmp:
        onnx.save(model, str(tmp))
    with AtomicFile(plan.sidecar) as tmp:
        tmp.write_text(json.dumps(sidecar, indent=2) + "\n")
    if priors is not None:
        save_priors(plan.priors_file, priors, CLASS_NAMES)
    priors_file = plan.priors_file if priors is not None else None
    return Exported(plan.output, plan.sidecar, priors_file, result)


def _load(plan: ExportPlan) -> tuple[torch.nn.Module, torch.Tensor | None, str]:
    from costseg.checkpoints import find_checkpoint
    from costseg.networks import load_costseg_checkpoint, load_network

    if plan.network is not None and not plan.network.startswith("costseg:"):
        return load_network(plan.network), None, plan.network
    spec = plan.network.removeprefix("costseg:") if plan.network else plan.ckpt_path
    path = find_checkpoint(spec)
    checkpoint = load_costseg_checkpoint(path)
    return checkpoint.network.eval(), checkpoint.priors, f"costseg:{path}"


def sample_inputs(
    size: tuple[int, int], batch: int = 2, seed: int = 0, regional: bool = False
) -> tuple[torch.Tensor, ...]:
    """Random uint8 images of ``size`` with the symmetric matrix, no priors (ones) and
    temperature 1: inputs of the graph. ``regional``: the packaged ``street_person.yaml``
    stack (:data:`REGIONAL_EXAMPLE`) and the geometric RoI map at half the images' size, in
    place of the matrix.

    >>> [tuple(t.shape) for t in sample_inputs((4, 6))]
    [(2, 3, 4, 6), (19, 19), (19, 1, 1), ()]
    >>> [tuple(t.shape) for t in sample_inputs((4, 6), regional=True)]
    [(2, 3, 4, 6), (5, 19, 19), (19, 1, 1), (), (2, 3)]
    """
    gen = torch.Generator().manual_seed(seed)
    image = torch.randint(0, 256, (batch, 3, *size), generator=gen, dtype=torch.uint8)
    common = (torch.ones(NUM_CLASSES, 1, 1), torch.tensor(1.0))
    if not regional:
        return image, symmetric_cost(NUM_CLASSES, torch.float32), *common
    stack = load_cost(COSTS_DIR / REGIONAL_EXAMPLE).float()
    roi = geometric_roi_map((max(1, size[0] // 2), max(1, size[1] // 2))).to(torch.uint8)
    return image, stack, *common, roi


REGIONAL_EXAMPLE = "street_person.yaml"
"""The regional cost file the graph of ``--regional`` is traced and checked with."""


def trace_graph(graph: DecisionGraph):
    """The graph as an ONNX model (in memory), every output dynamic in batch, height, width (a
    regional graph: the stack's matrices and the RoI map's size too)."""
    import io

    import onnx

    axes = {0: "batch", 2: "height", 3: "width"}
    maps = {0: "batch", 1: "height", 2: "width"}
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        # The shape checks of ImageNetwork are constants of the trace (the checked size below
        # confirms the graph generalises); the TorchScript-based exporter is deprecated in
        # favour of torch.export, which cannot export dynamic heights and widths here.
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        regional = {"cost": {0: "regions", 1: "rows"}, "roi": {0: "roi_height", 1: "roi_width"}}
        torch.onnx.export(
            graph,
            sample_inputs(TRACE_SIZE, regional=graph.regional),
            buffer,
            dynamo=False,
            opset_version=OPSET,
            input_names=list(REGIONAL_INPUTS if graph.regional else INPUTS),
            output_names=list(OUTPUTS),
            dynamic_axes={
                "image": axes,
                "cost": {0: "rows"},
                "priors": {1: "priors_height", 2: "priors_width"},
                "labels": maps,
                "margin": maps,
                "probabilities": axes,
                **(regional if graph.regional else {}),
            },
        )
    return onnx.load_from_string(buffer.getvalue())


def _check(graph: DecisionGraph, model) -> tuple[list[list[int]], Parity]:
    """Run the graph at a size other than the traced one against PyTorch; ValueError if a label
    differs beyond the bound of docs/definitions.md §19. Returns the sizes checked and the
    comparison."""
    from costseg.export.runtime import run_graph
    from costseg.networks.onnx import onnx_session

    image, cost, priors, temperature, *roi = sample_inputs(
        CHECK_SIZE, batch=1, seed=1, regional=graph.regional
    )
    roi = roi[0] if roi else None
    session = onnx_session(model.SerializeToString())
    labels, _, probs = run_graph(session, image, cost, priors, temperature, True, roi)
    with torch.no_grad():
        reference = graph.network(image).softmax(1)
    resized = None if roi is None else graph_roi(roi, CHECK_SIZE).view(CHECK_SIZE)
    result = parity(reference, probs, labels, cost, roi=resized)
    if result.outside:
        raise ValueError(
            f"the exported graph disagrees with PyTorch at {CHECK_SIZE[0]} x {CHECK_SIZE[1]} on "
            f"{result.outside} pixels beyond float32 rounding: not written"
        )
    return [list(CHECK_SIZE)], result


def _sidecar(
    plan: ExportPlan, network: Any, source: str, has_priors: bool, checked: list
) -> dict[str, Any]:
    """What a deployment needs beside the graph (docs/deploy.md)."""
    matrices = {name: load_cost(name).tolist() for name in PRESETS}
    return {
        "graph": plan.output.name,
        "source": source,
        "classes": list(CLASS_NAMES),
        "normalisation": {
            "inside the graph": True,
            "formula": "(image / divisor - mean) / std per RGB channel",
            "divisor": float(network.divisor),
            "mean": [float(f"{v:.7g}") for v in network.mean.flatten().tolist()],
            "std": [float(f"{v:.7g}") for v in network.std.flatten().tolist()],
        },
        "inputs": {
            "image": "(B, 3, H, W) uint8 RGB",
            "cost": "(N, N) float32, rows: decisions, columns: true classes; or (N + 1, N) "
            "with a defer row last",
            "priors": "(N, H, W) or (N, 1, 1) float32 > 0; ones (N, 1, 1) for rules without priors",
            "temperature": "() float32 > 0; 1: the network's own softmax",
            **(REGIONAL_SIDECAR if plan.regional else {}),
        },
        "outputs": {
            "labels": "(B, H, W) uint8 train ids, 255 = deferred",
            "margin": "(B, H, W) float32, second smallest minus smallest expected cost",
            **({"probabilities": "(B, N, H, W) float32"} if plan.probabilities else {}),
        },
        "sizes": {
            "height and width": "any the network accepts (dynamic), the labels at the input size",
            "traced at": list(TRACE_SIZE),
            "checked against PyTorch at": checked,
        },
        "rules": {
            **{name: {"cost": matrices[name], "priors": False} for name in PRESETS},
            "ml": {"cost": symmetric_cost(NUM_CLASSES).tolist(), "priors": True},
        },
        "priors": plan.priors_file.name if has_priors else None,
        "regional": plan.regional,
        "opset": OPSET,
    }


REGIONAL_SIDECAR = {
    "cost": "(K, N, N) float32, a regional value system's stack (docs/definitions.md §21): "
    "matrix 0 the default, matrix r that of RoI r; or (K, N + 1, N) with defer rows; (1, N, N) "
    "with a RoI map of zeros: one matrix everywhere",
    "roi": "(h, w) uint8 RoI ids < K (0 none, 1 street, 2 sidewalk, 3 building, 4 sky), of the "
    "images' shape at any size: the graph resizes it to the labels (nearest neighbour)",
}
"""The sidecar's inputs of a ``--regional`` graph that differ from a plain one's."""
