"""The pixel-wise priors of an evaluation's data (docs/definitions.md §3, §8), decided by the plan:
a ``--priors`` file; the source's own when they were counted on this data; else counted once from
the data's train labels and cached. Each comes with its record for results.json's ``source``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from costseg.classes import CLASS_NAMES
from costseg.data.from_config import same_data


def no_priors(data: str | None, geometric: bool = True) -> str:
    """The one line that refuses a run whose data has no priors to offer (``data`` None: a
    dataset given in Python, whose keywords it names)."""
    if data is None:
        return (
            "no pixel-wise priors for the given dataset: pass priors= (a (19, H, W) tensor, or a "
            "run's priors.pt)"
            + (' or roi="geometric" (then no ml, no alpha_sweep)' if geometric else "")
        )
    return (
        f"no pixel-wise priors for {data}: no train split to count them from (gtFine/train); "
        "pass --priors FILE (a run's priors.pt, or scripts/count_priors.py's from a label folder)"
        + (" or --roi geometric (then no ml, no --alpha_sweep)" if geometric else "")
    )


def evaluation_priors(
    source,
    priors_file: str | None,
    geometric: bool,
    data: dict | None,
    cache_dir: Path,
    progress: bool,
) -> tuple[torch.Tensor | None, Any]:
    """(priors, their record) of the evaluated ``data``: the ``priors_file``; the source's own
    when they were counted on this data (a checkpoint's, or those saved beside probabilities;
    for a dataset given in Python, ``data`` None, those given with it; record None: the
    source's description says where they come from); else counted once from the data's train
    labels and cached in ``cache_dir`` (next to the outputs). None only when ``geometric`` (the
    RoIs of ``--roi geometric``) and there are no train labels; never another dataset's
    priors."""  # fmt: skip
    if priors_file is not None:
        from costseg.data.priors import read_priors_file

        priors = read_priors_file(priors_file, CLASS_NAMES)["priors"]
        print(f"priors read from {priors_file}")
        return priors, {"file": str(Path(priors_file).resolve())}
    if source.priors is not None and (data is None or same_data(source.data_config, data)):
        return source.priors, None
    if source.priors is not None:
        print("the source's priors were counted on other data: not used for this data")
    return _counted_priors(geometric, data, cache_dir, progress)


def _counted_priors(
    geometric: bool, data: dict | None, cache_dir: Path, progress: bool
) -> tuple[torch.Tensor | None, Any]:
    from costseg.data.from_config import build_dataset, data_settings
    from costseg.data.priors_cache import settings_key, training_priors

    try:
        if data is None:
            raise FileNotFoundError("a dataset given in Python has no train split")
        train = build_dataset(data, "train")
    except FileNotFoundError:
        if geometric:
            print("no training labels: no pixel-wise priors; RoIs from the geometric map")
            return None, "none: no training labels"
        raise ValueError(no_priors(None if data is None else data_settings(data).root)) from None
    read = getattr(train, "read_label", None) or (lambda i: train[i][1])
    found = training_priors(
        lambda: (read(i) for i in range(len(train))),
        cache_dir / f"train_{settings_key(data)}.pt",
        {"data": data, "split": "train", "images": len(train)},
        progress=progress,
    )
    return found.priors, found.record | {"data": data, "split": "train"}
