"""The options of ``evaluate.py`` as one typed value (no heavy imports: ``--help`` stays fast)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class EvalOptions:
    """Everything ``evaluate.py`` can be told (see ``python evaluate.py --help``)."""

    cost: list[str] = field(default_factory=lambda: ["robotistic", "altruistic", "egoistic"])
    ckpt_path: str | None = None
    network: str | None = None
    probs: str | None = None
    data_root: str | None = None
    split: str = "val"
    classes: list[str] = field(default_factory=lambda: ["person", "building"])
    output_dir: str | None = None
    overwrite: bool = False
    limit: int | None = None
    batch_size: int | None = None
    device: str = "auto"
    save_predictions: bool = False
    save_probs: bool = False
    num_examples: int = 3
    sweep: float | None = None
    vertices: list[str] = field(default_factory=lambda: ["robotistic", "altruistic", "egoistic"])
    vertex_scaling: str = "none"
    target: str | None = None
    maximize: str | None = None
    alpha_sweep: float | None = None
    alpha_cost: str | None = None
    calibrate: str | None = None
    calibration_split: str | None = None
    temperature_sweep: bool = False
    guarantee: float | None = None
    guarantee_method: str = "bonferroni"
    mc_dropout: int | None = None
    seed: int = 0
    progress: bool = True
