"""Priors computed once and cached (docs/definitions.md §3, §8): by train.py once per dataset,
beside the runs folder, by evaluate.py for networks costseg did not train or other data, next to
its outputs."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from torch import Tensor

from costseg.classes import CLASS_NAMES, NUM_CLASSES
from costseg.data.priors import (
    count_pixel_priors,
    normalise_settings,
    read_priors_file,
    save_priors,
)


class CachedPriors(NamedTuple):
    """What :func:`cached_priors` returns: the priors and how they were obtained."""

    priors: Tensor
    """(N, H, W) float32 priors."""
    num_labels: int
    """Training labels counted."""
    sigma: float
    """Smoothing σ in pixels actually used."""
    reused: bool
    """True when read from the cache file, False when computed now."""

    @property
    def record(self) -> dict[str, Any]:
        """How they were counted, for the outputs' description of the priors."""
        return {"labels": self.num_labels, "sigma_px": self.sigma}


def settings_key(settings: Any) -> str:
    """A cache file's name for JSON-like ``settings``: 12 hex digits of their SHA-1 (keys
    sorted; objects JSON does not know by ``str``).

    >>> settings_key({"b": 1, "a": [2]}) == settings_key({"a": [2], "b": 1})
    True
    """
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def training_priors(
    labels: Callable[[], Iterable[Tensor]],
    cache_file: str | Path,
    settings: Mapping[str, Any],
    **counting: Any,
) -> CachedPriors:
    """The priors of a dataset's training labels, the one way train.py and evaluate.py obtain
    them: :func:`cached_priors` in ``cache_file`` (name it with :func:`settings_key`), and one
    line saying whether they were reused or counted now.

    Args:
        labels, cache_file, settings: As for :func:`cached_priors`.
        **counting: ``num_classes``, ``sigma``, ``class_names``, ``progress`` ... of
            :func:`cached_priors`.
    """
    found = cached_priors(labels, cache_file, settings, **counting)
    verb = "reused" if found.reused else "computed"
    print(f"priors {verb} from {found.num_labels} training labels (σ = {found.sigma:g} px)")
    return found


def cached_priors(
    labels: Callable[[], Iterable[Tensor]],
    cache_file: str | Path,
    settings: Mapping[str, Any],
    num_classes: int = NUM_CLASSES,
    sigma: float | None = None,
    eps: float = 1e-5,
    class_names: Sequence[str] = CLASS_NAMES,
    max_labels: int | None = None,
    progress: bool = True,
) -> CachedPriors:
    """Priors from ``cache_file`` when it was made with the same settings, else computed and saved.

    For a network costseg did not train: the priors come from the dataset's training labels
    (docs/definitions.md §3, §8), computed once with a progress bar. The file records ``settings``
    (say the
    dataset root, split and label size) together with ``num_classes``, ``sigma``, ``eps`` and
    ``max_labels``; any difference, an unreadable file or other classes mean a recomputation.

    Args:
        labels: Called only when computing; returns the (H, W) label maps (see
            :func:`pixel_priors`).
        cache_file: The ``.pt`` file (written atomically).
        settings: JSON-like description of the label source; tuples and lists compare equal,
            other objects by ``str``.
        num_classes, sigma, eps, max_labels, progress: As for :func:`pixel_priors`.
        class_names: Class name per channel, stored and checked.

    Returns:
        :class:`CachedPriors`.

    >>> import tempfile, torch
    >>> folder = tempfile.mkdtemp()
    >>> make = lambda: [torch.tensor([[0, 1]])]
    >>> two = {"num_classes": 2, "class_names": ["road", "sky"]}
    >>> first = cached_priors(make, f"{folder}/p.pt", {"split": "train"}, **two)
    >>> again = cached_priors(make, f"{folder}/p.pt", {"split": "train"}, **two)
    >>> first.reused, again.reused, torch.equal(first.priors, again.priors), again.num_labels
    (False, True, True, 1)
    """
    wanted = normalise_settings(
        {**settings, "costseg": {"num_classes": num_classes, "sigma": sigma, "eps": eps,
                                 "max_labels": max_labels}}
    )  # fmt: skip
    try:
        payload = read_priors_file(cache_file, class_names)
    except (FileNotFoundError, ValueError):
        payload = None  # no usable cache: compute below
    if payload is not None and (payload.get("settings") or {}).get("request") == wanted:
        info = payload["settings"]
        return CachedPriors(payload["priors"], info["num_labels"], info["sigma_px"], True)
    pi, count, used_sigma = count_pixel_priors(
        labels(), num_classes, sigma, eps, progress, max_labels
    )
    record = {"request": wanted, "num_labels": count, "sigma_px": used_sigma}
    save_priors(cache_file, pi, class_names, settings=record)
    return CachedPriors(pi, count, used_sigma, False)
