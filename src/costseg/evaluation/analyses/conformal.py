"""``--conformal ALPHA``: prediction sets anchored on each named rule's decision, their λ chosen
by conformal risk control on the held-out images so that the expected loss on new images is at
most α (docs/definitions.md §18); on the reported images their loss, sizes and coverage."""

from __future__ import annotations

from dataclasses import fields

import torch

from costseg.calibration.conformal import (
    RiskControl,
    SetCounts,
    conformity_scores,
    crc_threshold,
    lambda_grid,
    set_losses,
)
from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.evaluation.analyses import Analysis, Seen
from costseg.evaluation.processes import in_image_order, summed
from costseg.evaluation.settings import ConformalSettings
from costseg.report.conformal import ConformalOutputs, RuleSets
from costseg.rules import named_group


class Conformal(Analysis):
    settings: ConformalSettings

    def fit(self) -> None:
        self.rules = named_group(self.context.groups).rules
        self.grid = lambda_grid()
        losses = [[] for _ in self.rules]
        with torch.inference_mode():
            for seen in self.context.held_out_seen("conformal risk control"):
                for k, loss in enumerate(self._held_out_losses(seen)):
                    losses[k].append(loss.cpu())
        self.control: list[RiskControl] = [
            crc_threshold(torch.cat(mine).numpy(), self.grid.numpy(), self.settings.alpha)
            for mine in losses
        ]

    def start(self) -> None:
        device = self.context.plan.device
        self.counts = [SetCounts.zeros(len(CLASS_NAMES), NUM_ROIS, device) for _ in self.rules]
        self.reported = [[] for _ in self.rules]  # per rule: (position, loss) of each image
        self.example = None

    def process(self, seen: Seen) -> None:
        labels, sizes = seen.batch.labels, []
        for k, (control, counts) in enumerate(zip(self.control, self.counts, strict=True)):
            scores = conformity_scores(seen.probs, seen.named[:, k], self.settings.sets)
            counts.add(scores, labels, control.lam, seen.roi)
            lam = torch.tensor([control.lam], dtype=torch.float64)
            losses = self._loss(scores, labels, seen.roi, lam, k)[:, 0].cpu()
            self.reported[k] += zip(seen.positions, losses.tolist(), strict=True)
            if seen.positions[0] == 0:  # the first image's set sizes, for its figure
                sizes.append((scores[0] <= control.lam).sum(0).cpu())
        if sizes:
            self.example = (seen.batch.images[0].cpu(), seen.batch.stems[0], sizes)

    def gather(self) -> None:
        self.example = in_image_order([] if self.example is None else [(0, self.example)])[0]
        self.counts = [
            SetCounts(*(summed(getattr(c, f.name)) for f in fields(c))) for c in self.counts
        ]
        self.reported = [
            torch.tensor(in_image_order(mine), dtype=torch.float64) for mine in self.reported
        ]

    def result(self) -> ConformalOutputs:
        rules = []
        for rule, control, counts, losses in zip(
            self.rules, self.control, self.counts, self.reported, strict=True
        ):
            rules.append(RuleSets(rule.name, control, counts, losses))
        return ConformalOutputs(
            self.settings.alpha, self._describe(), self.grid, rules, self.example
        )

    def _held_out_losses(self, seen: Seen) -> list[torch.Tensor]:
        """Per named rule, the (B, L) losses on the grid of a held-out batch's images."""
        kind, labels, preds = self.settings.sets, seen.batch.labels, seen.named
        return [
            self._loss(
                conformity_scores(seen.probs, preds[:, k], kind), labels, seen.roi, self.grid, k
            )
            for k in range(len(self.rules))
        ]

    def _loss(self, scores, labels, roi, grid, k: int) -> torch.Tensor:
        """(B, L) losses of rule k's sets (conformity ``scores``) at each λ of ``grid``."""
        given = self.settings
        mask = None if given.roi is None or roi is None else (roi == given.roi).expand_as(labels)
        grid = grid.to(scores.device)
        return set_losses(scores, labels, grid, given.loss, self.rules[k].cost, given.tau, mask)

    def _describe(self) -> str:
        given = self.settings
        loss = {
            "uniform": "the share of labelled pixels whose class is not in the set",
            "cost": "the share of labelled pixels whose class is not in the set, each weighted "
            "by the anchor rule's mean cost of missing its class",
            "binary": f"1 when less than {given.tau:g} of the labelled pixels are covered",
        }[given.loss]
        where = "" if given.roi is None else f" in RoI {given.roi}"
        return f"{given.sets.upper()} sets; loss of an image: {loss}{where}"


ANALYSIS = Conformal
