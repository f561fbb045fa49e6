"""Maximum likelihood against Bayes on a trained model: pixel-wise vs global priors, and where
pixel-wise ML sends the person pixels of the street RoI.

    python scripts/ml_priors.py [--ckpt_path PATH] [--split val]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, class_index
from costseg.cli import parse_options, user_errors
from costseg.data.from_config import build_dataset
from costseg.data.prior_maps import PriorMaps
from costseg.decision import decide
from costseg.metrics import RoIPrecisionRecall
from costseg.networks import load_costseg_checkpoint
from costseg.options import SourceOptions, option, same_option

RULES = ("bayes", "ml, pixel-wise priors", "ml, global priors")


@dataclass
class PriorsOptions:
    """What ``ml_priors.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="a train.py checkpoint (default: the newest runs/**/last.ckpt)", metavar="PATH"
    )
    split: Literal["train", "val", "test"] = same_option(SourceOptions, "split")


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(PriorsOptions, args, "ml_priors.py", __doc__.splitlines()[0])
    ckpt = load_costseg_checkpoint(find_checkpoint(args.ckpt_path))
    dataset = build_dataset(ckpt.data_config, args.split)
    maps, person = PriorMaps(ckpt.priors), class_index("person")
    glob = ckpt.priors.mean((1, 2))
    metric = RoIPrecisionRecall(19, num_rules=3)
    taken, ratios = torch.zeros(19, dtype=torch.long), []
    with torch.inference_mode():
        for i in range(len(dataset)):
            image, label = dataset[i]
            probs = ckpt.network.eval()(image[None]).softmax(1)
            priors, roi = maps.at(tuple(label.shape))
            ml = decide(probs, None, priors)
            metric.update(
                torch.stack([decide(probs), ml, decide(probs, None, glob)], 1), label[None], roi
            )
            street_person = (label == person) & (roi == 1)
            taken += torch.bincount(ml[0][street_person], minlength=19)
            lost = (street_person & (ml[0] != person)).nonzero(as_tuple=True)
            if len(lost[0]):
                rows, cols = lost
                chosen = priors[ml[0][lost], rows, cols]
                ratios.append((priors[person][lost] / chosen).median())
    out = metric.compute()
    floor = (ckpt.priors <= 1.01e-5).float().mean()
    print(f"{len(dataset)} {args.split} images; priors {ckpt.extra.get('priors_info')}, "
          f"{100 * floor:.1f} % of entries at the 1e-5 floor")  # fmt: skip
    for k, name in enumerate(RULES):
        recall, precision = out["recall"][k, 1, person], out["precision"][k, 1, person]
        print(f"  {name:22s} mIoU {100 * out['miou'][k]:6.2f}   person, street RoI: "
              f"recall {100 * recall:6.2f} precision {100 * precision:6.2f}")  # fmt: skip
    share = taken.double() / taken.sum()
    top = ", ".join(
        f"{CLASS_NAMES[c]} {100 * share[c]:.1f} %" for c in share.argsort(descending=True)[:4]
    )
    print(f"pixel-wise ML labels the street-RoI person pixels: {top}")
    ratio = torch.stack(ratios).median()
    print(f"median π(person) / π(class ML chose) at the person pixels it lost: {ratio:.0f}")


if __name__ == "__main__":
    with user_errors():
        main()
