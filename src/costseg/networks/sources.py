"""Where the probabilities come from: a network (costseg, VainF, transformers) or saved files.

Every source maps a batch of (B, 3, H, W) uint8 images, with their image names, to (B, N, H, W)
scores: logits from a network, probabilities from files. The evaluation loop turns them into
the probabilities the rules see (softmax, calibration, float16 rounding for ``--save-probs``).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from costseg import workers
from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.data.from_config import image_stems
from costseg.networks.base import resize_bilinear
from costseg.progress import progress


@dataclass
class Source:
    """A probability source.

    Attributes:
        kind: "network" (``scores`` are logits) or "probs" (``scores`` are probabilities).
        description: what it is, for every output (spec, path).
        network: for kind "network", the module mapping uint8 images to logits.
        probs_dir: for kind "probs", the folder of per-image files.
        priors: (N, H, W) pixel-wise priors stored with a costseg checkpoint (or saved beside
            probabilities), else None; they belong to ``data_config``'s data.
        data_config: the dataset a costseg checkpoint was trained on (or whose images saved
            probabilities are), else None.
        run_dir: the training run's folder of a costseg checkpoint (default output place).
        probabilities: what the scores are when not a network's logits (saved probabilities,
            Monte-Carlo dropout), for every output.
        resized_to_labels: the size pairs met while scoring where the scores were resized to
            the labels' size (``at_label_size``), for every output.
    """

    kind: str
    description: dict[str, Any]
    network: torch.nn.Module | None = None
    probs_dir: Path | None = None
    priors: Tensor | None = None
    data_config: dict[str, Any] | None = None
    run_dir: Path | None = None
    probabilities: str | None = None
    resized_to_labels: list[str] = field(default_factory=list)

    def default_output(self, job: str, elsewhere: str) -> Path:
        """Where a job's numbered output folders go by default: ``<run>/<job>`` beside a costseg
        checkpoint, else ``<elsewhere>/<the network's or folder's name>``."""
        if self.run_dir is not None:
            return self.run_dir / job
        name = str(next(iter(self.description.values()))).split(":")[-1].split("?")[0].rstrip("/")
        name = "ensemble" if "members" in self.description else Path(name).stem
        return Path(elsewhere) / (name or "network")

    def probabilities_of(self, scores: Tensor) -> Tensor:
        """The probabilities of this source's ``scores``: the softmax of logits, or themselves."""
        return scores if self.kind == "probs" else scores.softmax(1)

    def logits_of(self, scores: Tensor) -> Tensor:
        """The logits of this source's ``scores``: themselves, or ``log p`` of probabilities."""
        return scores if self.kind == "network" else scores.clamp_min(1e-30).log()

    def scores(
        self, images: Tensor, stems: list[str], size: tuple[int, int] | None = None
    ) -> Tensor:
        """(B, N, H, W) float logits (network) or probabilities (files, Monte-Carlo dropout) at
        the images' size; saved probabilities are read at ``size`` (the labels'), default the
        images'."""
        if self.network is not None and self.kind == "probs":  # MCDropout, seeded by the names
            return self.network(images, stems).float()
        if self.network is not None:
            return self.network(images).float()
        from costseg.networks.probs_files import find_probs_file, load_probs

        assert self.probs_dir is not None
        size = tuple(size or images.shape[-2:])
        files = [find_probs_file(self.probs_dir, stem) for stem in stems]
        probs = [load_probs(f, len(CLASS_NAMES), size=size) for f in files]
        return torch.stack(probs).to(images.device)

    def scores_and_entropy(
        self, images: Tensor, stems: list[str], size: tuple[int, int] | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """:meth:`scores` (``size`` as there), and E_t H(p_t) (B, H, W) where the source averages
        several runs (Monte-Carlo dropout's passes, an ensemble's members;
        ``docs/definitions.md §13``), else None."""
        average = getattr(self.network, "average", None)
        if average is None:
            return self.scores(images, stems, size), None
        runs = average(images, stems)
        return runs.mean.float(), runs.expected_entropy

    def at_label_size(
        self, scores: Tensor, expected_entropy: Tensor | None, size: tuple[int, int]
    ) -> tuple[Tensor, Tensor | None]:
        """``scores`` (and the expected entropy) brought to the labels' ``size`` (H, W) as the
        official evaluators score, at label resolution: bilinear on logits, or on probabilities
        where the source gives probabilities (a convex combination, so they still sum to 1).
        The first time a size pair is met it is said on the terminal and kept in
        ``resized_to_labels`` (results.json)."""
        if tuple(scores.shape[-2:]) == tuple(size):
            return scores, expected_entropy
        pair = f"{scores.shape[-2]}x{scores.shape[-1]} -> {size[0]}x{size[1]}"
        if pair not in self.resized_to_labels:
            what = "logits" if self.kind == "network" else "probabilities"
            print(f"images and labels differ in size: {what} resized bilinearly {pair}")
            self.resized_to_labels.append(pair)
        scores = resize_bilinear(scores, size)
        if expected_entropy is not None:
            expected_entropy = resize_bilinear(expected_entropy[:, None], size)[:, 0]
        return scores, expected_entropy


def open_source(
    ckpt_path: str | None, network: str | None, probs: str | None, device: torch.device
) -> Source:
    """The source the options name: ``--network SPEC``, ``--probs DIR`` or a costseg checkpoint
    (``--ckpt_path``, default the newest ``runs/**/last.ckpt``)."""
    if probs is not None:
        from costseg.networks.probs_files import read_data_record

        folder = Path(probs)
        if not folder.is_dir():
            raise FileNotFoundError(f"--probs folder not found: {probs}")
        data, priors = read_data_record(folder)
        return Source(
            "probs",
            {"probs": str(folder)},
            probs_dir=folder,
            priors=priors,
            data_config=data,
            probabilities="saved probabilities",
        )
    if network is not None and not network.startswith("costseg:"):
        from costseg.networks import load_network

        net = load_network(network, device=str(device))
        return Source("network", {"network": network}, network=net)
    path = find_checkpoint(network.removeprefix("costseg:") if network else ckpt_path)
    return _costseg_source(path, device)


def _costseg_source(path: Path, device: torch.device) -> Source:
    from costseg.networks import load_costseg_checkpoint

    print(f"checkpoint: {path}")
    checkpoint = load_costseg_checkpoint(path)
    return Source(
        "network",
        {
            "network": f"costseg:{path}",
            "hparams": checkpoint.hparams,
            "priors": checkpoint.extra.get("priors_info") or "stored in the checkpoint",
        },
        network=checkpoint.network.to(device).eval(),
        priors=checkpoint.priors,
        data_config=checkpoint.data_config,
        run_dir=path.parent.parent,
    )


def with_mc_dropout(source: Source, passes: int | None, seed: int) -> Source:
    """``source`` giving Monte-Carlo dropout probabilities (``docs/definitions.md §12``) when
    ``passes`` is set; ValueError for saved probabilities or a network without dropout."""
    if passes is None:
        return source
    if source.network is None:
        raise ValueError("--mc_dropout needs a network: saved probabilities cannot be resampled")
    from costseg.networks.mc_dropout import MCDropout

    net = MCDropout(source.network, passes, seed)
    source.kind, source.network, source.probabilities = "probs", net, net.describe()
    source.description["mc_dropout"] = {"passes": passes, "seed": seed}
    return source


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA when present), ``cpu``, ``cuda``, ``cuda:1``, ...; ValueError if unusable.

    >>> resolve_device("cpu")
    device(type='cpu')
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}: expected auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"device {name!r} is not available: this machine has no CUDA GPU")
        if device.index is not None and device.index >= count:
            raise ValueError(f"device {name!r} is not available: this machine has {count} GPU(s)")
    elif device.type != "cpu":
        raise ValueError(f"device {name!r} is not supported: expected auto, cpu, cuda or cuda:N")
    return device


@dataclass
class Batch:
    """Images of one size with their labels, names and the source's scores, on the device."""

    images: Tensor  # (B, 3, H, W) uint8, at the labels' size (resized when the files differ)
    labels: Tensor  # (B, H, W) int64
    stems: list[str]
    scores: Tensor  # (B, N, H, W) logits or probabilities (see Source.kind)
    instances: Tensor | None = None  # (B, H, W) int64 instance ids, where the dataset has them
    expected_entropy: Tensor | None = None  # (B, H, W) E_t H(p_t) over several runs, else None
    anomalies: Tensor | None = None  # (B, H, W) anomaly masks (1, 0, 255), where the data has them


def batches(
    source: Source,
    dataset: Dataset,
    indices: Sequence[int],
    batch_size: int,
    device: torch.device,
    num_workers: int = 0,
    desc: str | None = None,
    entropy_images: int | None = None,
) -> Iterator[Batch]:
    """Score the chosen images of ``dataset``, batch by batch (a progress bar when ``desc``),
    with the expected entropy of a source of several runs for the batches that begin within the
    first ``entropy_images`` images (None: every batch; the entropy costs a pass per run).

    Images of different sizes (Mapillary, a user's own data) come in separate batches. Datasets
    with ``has_instances`` give each batch its instance ids (``docs/definitions.md §9``), those
    with ``has_anomalies`` also its anomaly masks (§17).
    """
    loader = DataLoader(
        _Indexed(dataset, list(indices)),
        batch_size=batch_size,
        collate_fn=_collate_by_size,
        **workers.loader_options(num_workers),
    )
    seen = 0
    with workers.loader_errors(f"{len(indices)} images"):
        for group in progress(loader, desc):
            for images, labels, chosen, ids, masks in group:
                images, labels = images.to(device), labels.to(device)
                stems = image_stems(dataset, chosen)
                ids = None if ids is None else ids.to(device)
                masks = None if masks is None else masks.to(device)
                size = tuple(labels.shape[-2:])
                if entropy_images is None or seen < entropy_images:
                    scores, expected_entropy = source.scores_and_entropy(images, stems, size)
                else:
                    scores, expected_entropy = source.scores(images, stems, size), None
                scores, expected_entropy = source.at_label_size(scores, expected_entropy, size)
                if images.shape[-2:] != labels.shape[-2:]:  # figures draw on the labels' grid
                    images = resize_bilinear(images.float(), size).round().to(torch.uint8)
                seen += len(images)
                yield Batch(images, labels, stems, scores, ids, expected_entropy, masks)


class _Indexed(Dataset):
    """(image, label, index, instance ids or None, anomaly mask or None) of the chosen items of a
    dataset."""

    def __init__(self, dataset: Dataset, indices: list[int]) -> None:
        self.dataset, self.indices = dataset, indices
        self.instances = bool(getattr(dataset, "has_instances", False))
        self.anomalies = bool(getattr(dataset, "has_anomalies", False))

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        index = self.indices[i]
        if self.anomalies:
            image, label, ids, mask = self.dataset.with_anomalies(index)
            return image, label, index, ids, mask
        if self.instances:
            image, label, ids = self.dataset.with_instances(index)
            return image, label, index, ids, None
        image, label = self.dataset[index]
        return image, label, index, None, None


def _collate_by_size(items) -> list[tuple]:
    """A batch as sub-batches of equal image and label sizes (datasets may mix resolutions):
    (images, labels, indices, instance ids or None, anomaly masks or None)."""
    by_size: dict[tuple[int, ...], list] = {}
    for item in items:
        by_size.setdefault((*item[0].shape, *item[1].shape), []).append(item)
    return [
        (
            torch.stack([i[0] for i in same]),
            torch.stack([i[1] for i in same]),
            [i[2] for i in same],
            None if same[0][3] is None else torch.stack([i[3] for i in same]),
            None if same[0][4] is None else torch.stack([i[4] for i in same]),
        )
        for same in by_size.values()
    ]
