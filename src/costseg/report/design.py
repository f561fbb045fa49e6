"""A value system designed from requirements (docs/definitions.md §20): ``designed_cost.yaml``
(the certified matrix, with its certificate as a header), ``design.json``,
``design_candidates.csv``, a table.md section and the figures."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from costseg.calibration.design_search import Candidates
from costseg.calibration.pareto_testing import ParetoTestingResult
from costseg.classes import CLASS_NAMES
from costseg.costs import load_cost, save_cost
from costseg.metrics.requirements import Requirements
from costseg.metrics.selection import metric_values
from costseg.report.design_figures import design_figures
from costseg.report.drawing import job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.rules import named_group, point_name

DESIGNED = "designed"
"""The designed matrix's rule name in the reported rows."""

DESIGNED_FAMILY = "designed"
"""The family of the rule group that holds the designed matrix and the best triangle point."""


@dataclass
class SearchOutcome:
    """One searched space: its candidates (scored on D1), Pareto Testing's outcome, the chosen
    candidate (None: nothing certified) and the objective on all held-out images (NaN off the
    front)."""

    candidates: Candidates
    testing: ParetoTestingResult
    chosen: int | None
    objective_all: np.ndarray
    designed: bool = True  # False: the triangle, searched beside another space to compare

    @property
    def rule_name(self) -> str:
        """The chosen matrix's name in the reported rows."""
        if self.designed:
            return DESIGNED
        weights = self.candidates.parameters[self.chosen, :3].tolist()
        return f"best triangle {point_name(weights)}"

    def record(self, req: Requirements) -> dict:
        """What design.json says of this search."""
        c, t = self.candidates, self.testing
        out = {
            "space": c.space,
            "parameters": list(c.names),
            "candidates": len(c.objective),
            "front": len(t.front),
            "certified": len(t.certified),
        }
        if self.chosen is not None:
            k = self.chosen
            return out | {
                "chosen": _candidate(c, t, k, req) | {"objective_held_out": self.objective_all[k]}
            }
        best = t.best
        failed = None if t.failed is None else req.texts[t.failed]
        return out | {
            "nothing_certified": _candidate(c, t, best, req)
            | {
                "failed_constraint": failed,
                "certification_images_needed": t.needed_images,
            }
        }

    def line(self, req: Requirements, delta: float) -> str:
        """One line for the terminal."""
        c, t = self.candidates, self.testing
        if self.chosen is None:
            if t.best is None:
                return "nothing certified (no candidate on the front)"
            failed = req.texts[t.failed]
            risks = ", ".join(f"{r:.3f}" for r in t.risks_d1[t.best])
            needed = (
                f"about {t.needed_images} certification images would let it pass"
                if t.needed_images
                else "its risk is above α: more images would not help"
            )
            return (
                f"nothing certified at δ = {delta}; the best search candidate has "
                f"risks {risks} on the search images and fails {failed} on the certification "
                f"images (p = {t.pvalues_d2[t.best, t.failed]:.3g}); {needed}"
            )
        k = self.chosen
        return (
            f"{len(t.certified)} of {len(c.objective)} candidates certified "
            f"(front {len(t.front)}); chosen {_parameters(c, k)}, certification risks "
            f"{', '.join(f'{r:.3f}' for r in t.risks_d2[k])}, {req.objective_text} "
            f"{self.objective_all[k]:.4f} on the held-out images"
        )


@dataclass
class DesignOutcome(Result):
    """The outcome of ``--design``: the requirements, δ, the split of the held-out images
    (the first ``n1`` searched, the other ``n2`` certify), the share of pixels searched, the seed,
    and each searched space (the design's first, then the triangle to compare)."""

    requirements: Requirements
    delta: float
    n1: int
    n2: int
    share: float
    seed: int
    searches: list[SearchOutcome]

    def write(self, results: EvalResults) -> Section:
        req, out, own = self.requirements, results.output_dir, self.searches[0]
        record = {
            "constraints": list(req.texts),
            "alphas": list(req.alphas),
            "objective": req.objective_text,
            "maximize": req.maximize,
            "delta": self.delta,
            "split": {
                "search (D1)": f"the first {self.n1} held-out images",
                "certification (D2)": f"the other {self.n2} held-out images",
                "reported": "the reported images, disjoint from both",
            },
            "search_pixels": self.share,
            "seed": self.seed,
            "searches": [s.record(req) for s in self.searches],
            "reported": _reported(results, self.searches, req),
        }
        if own.chosen is not None:
            matrix = own.candidates.matrices[own.chosen]
            save_cost(out / "designed_cost.yaml", matrix, DESIGNED, header=self._header(own))
            record["cost_file"] = "designed_cost.yaml"
        write_json(out / "design.json", record)
        write_csv(out / "design_candidates.csv", self._rows())
        lines = [
            f"design, {s.candidates.space} space{'' if s.designed else ' (to compare)'}: "
            + s.line(req, self.delta)
            for s in self.searches
        ]
        return Section(
            json={"design": record},
            table=self._table(record),
            console=lines,
            jobs=[("evaluation", self._figures(results))],
        )

    def _header(self, own: SearchOutcome) -> str:
        req, t, k = self.requirements, own.testing, own.chosen
        constraints = "; ".join(
            f"{text} (risk ≤ {a:.3g}; certification risk {r:.4f}, p = {p:.3g})"
            for text, a, r, p in zip(
                req.texts, req.alphas, t.risks_d2[k], t.pvalues_d2[k], strict=True
            )
        )
        return (
            f"designed by costseg evaluate.py --design {own.candidates.space} "
            f"(docs/definitions.md §20)\n"
            f"constraints: {constraints}\n"
            f"certificate: Pareto Testing, every constraint met jointly with probability "
            f">= {1 - self.delta:g} (δ = {self.delta}) over the draw of the certification images\n"
            f"search images n1 = {self.n1} ({self.share:g} of their pixels), certification images "
            f"n2 = {self.n2}; {len(own.candidates.objective)} candidates, front "
            f"{len(t.front)}, certified {len(t.certified)}\n"
            f"search space: {own.candidates.space}, parameters "
            f"{_parameters(own.candidates, k)}; objective {req.objective_text} = "
            f"{own.objective_all[k]:.4f} on the held-out images"
        )

    def _rows(self) -> list[dict]:
        req, rows = self.requirements, []
        for s in self.searches:
            c, t = s.candidates, s.testing
            tested = {int(i): rank for rank, i in enumerate(t.order)}
            certified = set(t.certified.tolist())
            for k in range(len(c.objective)):
                row = {"space": c.space, "candidate": k}
                row |= dict(zip(c.names, c.parameters[k].tolist(), strict=True))
                row |= {f"search risk {text}": t.risks_d1[k, i] for i, text in enumerate(req.texts)}
                row |= {
                    f"search {req.objective_text}": c.objective[k],
                    "front": k in tested,
                    "test order": tested.get(k, ""),
                    "certification p": t.pvalues_d2[k].max() if k in tested else math.nan,
                    "certified": k in certified,
                    "chosen": k == s.chosen,
                }
                rows.append(row)
        return rows

    def _table(self, record: dict) -> str:
        req = self.requirements
        lines = [
            "",
            f"## Designed value system (δ = {self.delta}; search on {self.n1} held-out images, "
            f"certification on {self.n2})",
            "",
            "| space | candidates | front | certified | chosen | "
            + " | ".join(f"{t} (certification risk)" for t in req.texts)
            + f" | {req.objective_text} (held-out) |",
            "|---" * (5 + len(req.texts) + 1) + "|",
        ]
        for s in self.searches:
            c, t, k = s.candidates, s.testing, s.chosen
            cells = [c.space, len(c.objective), len(t.front), len(t.certified)]
            if k is None:
                cells += ["none"] + ["–"] * len(req.texts) + ["–"]
            else:
                cells += [_parameters(c, k), *(f"{r:.4f}" for r in t.risks_d2[k])]
                cells += [f"{s.objective_all[k]:.4f}"]
            lines.append("| " + " | ".join(map(str, cells)) + " |")
        reported = record["reported"]
        if reported:
            rules = list(next(iter(reported.values())))
            lines += ["", "On the reported images:", "", "| constraint | " + " | ".join(rules)
                      + " |", "|---" * (len(rules) + 1) + "|"]  # fmt: skip
            for text, values in reported.items():
                lines.append(
                    f"| {text} | " + " | ".join(f"{v:.4f}" for v in values.values()) + " |"
                )
        return "\n".join(lines) + "\n"

    def _figures(self, results: EvalResults):
        from costseg.report.results import figure_subject

        req, own = self.requirements, self.searches[0]
        matrices = []
        if own.chosen is not None:
            matrices = [
                (DESIGNED, own.candidates.matrices[own.chosen]),
                ("robotistic", load_cost("robotistic")),
            ]
        fronts = []
        for s in self.searches:
            t = s.testing
            arguments = (t.risks_d1, s.candidates.objective, t.front, t.certified, s.chosen,
                         list(req.texts), list(req.alphas), req.objective_text)  # fmt: skip
            fronts.append((s.candidates.space, arguments))
        title = f"designed value system, {figure_subject(results.source, [])}"
        return job(design_figures, matrices, list(CLASS_NAMES), fronts, title)


def _candidate(c: Candidates, t: ParetoTestingResult, k: int, req: Requirements) -> dict:
    return {
        "index": int(k),
        "parameters": dict(zip(c.names, c.parameters[k].tolist(), strict=True)),
        "search_risks": dict(zip(req.texts, t.risks_d1[k].tolist(), strict=True)),
        "certification_risks": dict(zip(req.texts, t.risks_d2[k].tolist(), strict=True)),
        "certification_pvalues": dict(zip(req.texts, t.pvalues_d2[k].tolist(), strict=True)),
        "search_objective": float(c.objective[k]),
    }


def _parameters(c: Candidates, k: int) -> str:
    values = c.parameters[k].tolist()
    if len(values) > 6:  # the aggregate space: 30 costs
        return f"{len(values)} aggregate costs (design_candidates.csv)"
    return ", ".join(f"{n}={v:.3g}" for n, v in zip(c.names, values, strict=True))


def _reported(results: EvalResults, searches: list[SearchOutcome], req: Requirements) -> dict:
    """Per constraint, its value on the reported images for each named rule and each designed
    rule (the certified matrix, the best certified triangle point)."""
    designed = next((g for g in results.groups if g.group.family == DESIGNED_FAMILY), None)
    named = named_group([g.group for g in results.groups])
    groups = [results.result_of(named)] + ([designed] if designed is not None else [])
    out = {}
    for target in req.constraints:
        text = req.texts[req.constraints.index(target)]
        out[text] = {}
        for g in groups:
            try:
                values = metric_values(g.pixels, g.segments, target, results.class_ids,
                                       g.instances)  # fmt: skip
            except (ValueError, KeyError, IndexError):  # a rate not measured on these images
                values = torch.full((len(g.group.names),), math.nan)
            out[text] |= dict(zip(g.group.names, values.tolist(), strict=True))
    return out
