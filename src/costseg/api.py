"""costseg from Python: your own network on your own dataset or images, as ``evaluate.py`` and
``predict.py`` run them.

``costseg.evaluate`` and ``costseg.predict`` are this module's (imported on first use, so that
``import costseg`` stays light). Everything the command can be told is a keyword argument of
the same name (``sweep=0.1``, ``defer=0.3``, ``calibrate="temperature"``, ...; see
``python evaluate.py --help``), and the outputs go into a folder as the command's do. Figures are
drawn by worker processes of Python's forkserver: a script that calls it needs the usual
``if __name__ == "__main__":`` guard. docs/usage.md has a runnable example.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from costseg.classes import CLASS_NAMES
from costseg.data.priors import check_priors
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, ImageNetwork
from costseg.networks.sources import Source, resolve_device
from costseg.options import RULES, EvalOptions, PredictOptions
from costseg.report.results import EvalResults

__all__ = ["evaluate", "module_source", "predict"]


def evaluate(
    network: nn.Module | str,
    dataset: Dataset,
    costs: Sequence[str] = RULES,
    *,
    priors: Tensor | str | Path | None = None,
    mean: Sequence[float] = IMAGENET_MEAN,
    std: Sequence[float] = IMAGENET_STD,
    **options: Any,
) -> EvalResults | list[EvalResults]:
    """Evaluate ``network`` on ``dataset`` under the cost rules ``costs``.

    Args:
        network: a module mapping (B, 3, H, W) normalised float images to (B, 19, h, w) logits
            in Cityscapes' train-id order, or a dict holding them under ``"out"`` (torchvision's
            segmentation models), at the input size or a fraction of it (resized bilinearly);
            or a ``--network`` spec such as ``"costseg:runs/.../last.ckpt"``.
        dataset: items ``(image, label)``: (3, H, W) uint8 RGB and (H, W) int64 train ids
            (255 ignored), e.g. :class:`costseg.data.cityscapes.CityscapesSegmentation`.
            Images may have another size than their labels: scores are brought to the labels'.
        costs: the rules (``robotistic``, ``altruistic``, ``egoistic``, ``ml``, a YAML file).
        priors: pixel-wise priors of this data, (19, H, W) or a file written by costseg
            (docs/definitions.md §3), for ``ml`` and the RoI map; without them give
            ``roi="geometric"`` (the fixed map of a street camera) and no ``ml``.
        mean, std: the per-channel normalisation the network expects, of images in [0, 1].
        **options: any option of ``evaluate.py`` by its field name (``output_dir``,
            ``batch_size``, ``classes``, ``sweep``, ``defer``, ``roi``, ``device``, ...).

    Returns:
        the results (:class:`costseg.report.results.EvalResults`: ``output_dir``, ``groups``
        with their metrics and ``rows``), a list of them with several ``shift``.

    Raises:
        ValueError: an unknown option, a malformed item of ``dataset``, or what
            ``evaluate.py`` refuses.
    """
    from costseg.evaluation.plan import checked_groups
    from costseg.evaluation.run import evaluate as run_evaluation

    opts = _options(EvalOptions, network, costs, priors, options)
    groups = checked_groups(opts)  # evaluate.py's checks (each value's too), before the network
    _check_item(dataset)
    opener = _opener(network, mean, std, priors)
    source = None if opener is None else opener(resolve_device(opts.device))
    return run_evaluation(opts, source, dataset, groups)


def predict(
    network: nn.Module | str,
    inputs: Sequence[str | Path],
    costs: Sequence[str] = RULES,
    *,
    priors: Tensor | str | Path | None = None,
    mean: Sequence[float] = IMAGENET_MEAN,
    std: Sequence[float] = IMAGENET_STD,
    **options: Any,
) -> Path:
    """Apply the cost rules ``costs`` to ``network``'s probabilities on images without labels,
    as ``predict.py`` does (docs/predict.md): panels, label PNGs and counts per image.

    Args:
        network, costs, priors, mean, std: as for :func:`evaluate` (priors at any size: they
            are resized to each image's).
        inputs: images, folders (read recursively) and videos.
        **options: any option of ``predict.py`` by its field name.

    Returns:
        the output folder.
    """
    from costseg.prediction import job

    options["input"] = [str(path) for path in inputs]
    opts = _options(PredictOptions, network, costs, priors, options)
    return job.predict(opts, _opener(network, mean, std, priors))  # opened once checked


def _options(kind, network, costs, priors, options: dict[str, Any]):
    """The job's options (``kind``) of the keyword arguments; each job checks their values as
    it checks the command line's (:func:`costseg.options.check_values`)."""
    known = {f.name for f in dataclasses.fields(kind)} - {"cost", "priors"}
    unknown = sorted(set(options) - known)
    if unknown:
        names = ", ".join(sorted(known))
        raise ValueError(f"unknown option {unknown[0]!r}: expected one of {names}")
    if isinstance(network, str):
        options["network"] = [network]
    if isinstance(priors, (str, Path)):
        options["priors"] = str(priors)
    elif priors is not None:
        check_priors(priors, CLASS_NAMES, "the priors given")
    return kind(cost=list(costs) if isinstance(costs, (list, tuple)) else costs, **options)


def _opener(network, mean, std, priors) -> Callable[[torch.device], Source] | None:
    """What opens the source of a module given in Python on a device (None: the options name
    the network)."""
    if not isinstance(network, nn.Module):
        return None
    given = priors if isinstance(priors, Tensor) else None
    return lambda device: module_source(network, device, mean, std, given)


def module_source(
    network: nn.Module,
    device: torch.device,
    mean: Sequence[float] = IMAGENET_MEAN,
    std: Sequence[float] = IMAGENET_STD,
    priors: Tensor | None = None,
) -> Source:
    """A probability source of a module given in Python (behind its normalisation, unless it is
    an :class:`~costseg.networks.base.ImageNetwork` already), with the priors of its data."""
    if not isinstance(network, ImageNetwork):
        network = ImageNetwork(network, tuple(mean), tuple(std))
    described = {"network": f"python:{type(network.net).__name__}"}
    return Source("network", described, network=network.to(device).eval(), priors=priors)


def _check_item(dataset: Dataset) -> None:
    """ValueError unless ``dataset``'s first item is a (uint8 image, integer label) pair."""
    try:
        image, label = dataset[0][:2]
    except (TypeError, IndexError, ValueError) as err:
        raise ValueError(f"the dataset's items must be (image, label) pairs: {err}") from None
    if not (
        isinstance(image, Tensor) and image.dtype == torch.uint8 and image.ndim == 3
        and image.shape[0] == 3 and isinstance(label, Tensor) and label.ndim == 2
        and not label.is_floating_point()
    ):  # fmt: skip
        shapes = [getattr(t, "shape", type(t).__name__) for t in (image, label)]
        raise ValueError(
            "the dataset's items must be ((3, H, W) uint8 RGB image, (H, W) integer train ids); "
            f"its first item holds {shapes[0]} and {shapes[1]}"
        )
