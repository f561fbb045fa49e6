"""A value system designed from requirements (docs/definitions.md §20): ``designed_cost.yaml``
(the certified matrix, with its certificate as a header), ``design.json``,
``design_candidates.csv``, a table.md section, the console lines and the figures."""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field

import numpy as np
import torch

from costseg.calibration.design_search import Candidates
from costseg.calibration.pareto_testing import ParetoTestingResult
from costseg.classes import CLASS_NAMES, ROI_NAMES, roi_label
from costseg.costs import is_regional, load_cost, save_cost
from costseg.metrics.names import INSTANCE_RATES, SEGMENT_RATES
from costseg.metrics.requirements import Requirements
from costseg.metrics.selection import Target, metric_values
from costseg.report.certified import CERTIFIED_FOR, REQUIREMENT, fingerprint
from costseg.report.design_figures import design_figures
from costseg.report.drawing import job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.rules import named_group, point_name

DESIGNED = "designed"
"""The designed matrix's rule name in the reported rows."""

DESIGNED_FAMILY = "designed"
"""The family of the rule group that holds the designed matrix and the best matrix of each space
searched to compare."""


@dataclass(frozen=True)
class Split:
    """The held-out images of a design and their seeded split: ``d1`` searched, ``d2`` certify
    (positions among the held-out images, ascending), the names of all held-out images, and
    which images were held out, in words."""

    seed: int
    d1: list[int]
    d2: list[int]
    stems: list[str]
    held_out: str

    def record(self) -> dict:
        def names(positions: list[int]) -> list[str]:
            return [self.stems[p] if p < len(self.stems) else str(p) for p in positions]

        return {
            "held_out": self.held_out,
            "seed": self.seed,
            "how": "a random half of the held-out images, drawn with the seed "
            "(docs/definitions.md §20)",
            "search (D1)": {"count": len(self.d1), "positions": self.d1, "images": names(self.d1)},
            "certification (D2)": {
                "count": len(self.d2),
                "positions": self.d2,
                "images": names(self.d2),
            },
            "reported": "the reported images, disjoint from both",
        }


@dataclass
class SearchOutcome:
    """One searched space: its candidates (scored on D1), Pareto Testing's outcome, the chosen
    candidate (None: nothing certified), the objective on all held-out images (NaN off the
    front), the shares of labelled pixels the chosen (else the best) candidate defers on
    all held-out images (None without a defer row), and the share of labelled held-out pixels
    it decides otherwise than argmax (``changed``)."""

    candidates: Candidates
    testing: ParetoTestingResult
    chosen: int | None
    objective_all: np.ndarray
    designed: bool = True  # False: a space searched beside the design's to compare
    deferred: dict | None = None
    changed: float | None = None

    @property
    def rule_name(self) -> str:
        """The chosen matrix's name in the reported rows."""
        if self.designed:
            return DESIGNED
        if self.candidates.space != "triangle":
            return f"best {self.candidates.space}"
        weights = self.candidates.parameters[self.chosen, :3].tolist()
        return f"best triangle {point_name(weights)}"

    @property
    def shown(self) -> int | None:
        """The candidate the outputs describe: the chosen one, else the best uncertified."""
        return self.chosen if self.chosen is not None else self.testing.best

    def images(self, req: Requirements) -> dict[str, dict[str, int]]:
        """Per constraint, the search and certification images with a defined loss behind the
        shown candidate's risks."""
        t, k = self.testing, self.shown
        if k is None:
            return {}
        return {
            text: {"search": int(t.n_d1[k, i]), "certification": int(t.n_d2[k, i])}
            for i, text in enumerate(req.texts)
        }

    def record(self, req: Requirements, n1: int, n2: int) -> dict:
        """What design.json says of this search."""
        c, t = self.candidates, self.testing
        out = {
            "space": c.space,
            "search": c.how,
            "parameters": list(c.names),
            "candidates": len(c.objective),
            "front": len(t.front),
            "certified": len(t.certified),
            "images_with_a_defined_loss": self.images(req) | {"of": {"search": n1,
                                                                     "certification": n2}},
            "notes": self.notes(req),
        }  # fmt: skip
        if self.deferred is not None:
            out["deferred_share"] = self.deferred
        if self.changed is not None:
            out["changed_share"] = self.changed
        if self.chosen is not None:
            k = self.chosen
            return out | {
                "chosen": _candidate(c, t, k, req) | {"objective_held_out": self.objective_all[k]}
            }
        if t.best is None:
            return out | {"nothing_certified": None}
        failed = req.texts[t.failed]
        return out | {
            "nothing_certified": _candidate(c, t, t.best, req)
            | {
                "failed_constraint": failed,
                "certification_images_needed": t.needed_images,
                "why": self.why(req),
            }
        }

    def line(self, req: Requirements, delta: float, n2: int) -> str:
        """One line for the terminal."""
        c, t = self.candidates, self.testing
        if self.chosen is None:
            if t.best is None:
                return "nothing certified (no candidate on the front)"
            k = t.best
            return (
                f"nothing certified at δ = {delta}: the search's best candidate "
                f"({_parameters(c, k)}) has certification risks {_risks(t.risks_d2[k])} "
                f"(α {_risks(t.alphas)}) on {_counts(t.n_d2[k])} of {n2} images"
                f"{self._deferring()}; {self.why(req)}"
            )
        k = self.chosen
        return (
            f"{len(t.certified)} of {len(c.objective)} candidates certified "
            f"(front {len(t.front)}); chosen {_parameters(c, k)}, certification risks "
            f"{_risks(t.risks_d2[k])} on {_counts(t.n_d2[k])} of {n2} images, "
            f"{req.objective_text} {self.objective_all[k]:.4f} on the held-out images"
            f"{self._deferring()}"
        )

    def _deferring(self) -> str:
        if self.deferred is None:
            return ""
        return f", deferring {_share(self.deferred['all pixels'])} of the labelled held-out pixels"

    def why(self, req: Requirements) -> str:
        """Why the best candidate was not certified, and whether more images would help."""
        t, k = self.testing, self.testing.best
        i = t.failed
        text, target = req.texts[i], req.constraints[i]
        if np.isnan(t.risks_d1[:, i]).all():
            return (
                f"{text} is undefined on every search image under every candidate (no search "
                f"image {_where(target)} under any of them): it cannot be measured, let alone "
                f"certified; held-out images where it is defined are needed"
            )
        reached = np.nanmin(t.risks_d1[:, i])
        if not reached <= t.alphas[i]:
            return (
                f"no candidate of the space meets {text} even on the search images (its "
                f"smallest search risk is {reached:.3f} > α = {t.alphas[i]:.3g}): the space "
                f"cannot reach it" + _defer_hint(target, self.deferred is not None)
            )
        if t.n_d2[k, i] == 0:
            where = _where(target)
            more = (
                f" (about {t.needed_images} certification images at the search images' share "
                "of such images)"
                if t.needed_images
                else ""
            )
            return (
                f"{text} fails because no certification image {where}: its risk there is "
                f"undefined (p = 1), not above α; more images would help{more}"
            )
        p = t.pvalues_d2[k, i]
        if t.needed_images:
            return (
                f"{text} fails on the certification images (risk {t.risks_d2[k, i]:.3f}, "
                f"p = {p:.3g} > δ); about {t.needed_images} certification images at that risk "
                f"would let it pass"
            )
        return (
            f"{text} fails on the certification images: its risk {t.risks_d2[k, i]:.3f} there "
            f"is at or above α = {t.alphas[i]:.3g} (p = {p:.3g}); more images would not help"
            + _defer_hint(target, self.deferred is not None)
        )

    def notes(self, req: Requirements) -> list[str]:
        """What a reader should know of the shown candidate: a multiplier at an edge of the
        values searched (the top: a larger range might do better; the smallest above 0: a
        smaller one might), a recall that deferring can only lower."""
        c, k, out = self.candidates, self.shown, []
        if k is not None and c.space in ("lagrangian", "regional"):
            for i, text in enumerate(req.texts):
                out += _edge_note(c.parameters[:, i], k, i, text, c.how.startswith("a grid"))
        if self.deferred is not None:
            out += [
                f"{text}: a deferred pixel counts as a miss; handled_recall counts it as handled"
                for text, t in zip(req.texts, req.constraints, strict=True)
                if t.metric == "recall"
            ]
        return out


@dataclass
class DesignOutcome(Result):
    """The outcome of ``--design``: the requirements, δ, the held-out images and their seeded
    split, the share of pixels that measures the objective in the search, each searched space
    (the design's first, then the triangle to compare), the RoI map, the defer costs, and the
    reported images' per-image constraint losses of the named and designed rules (set by the
    analysis once the reported images are seen)."""

    requirements: Requirements
    delta: float
    split: Split
    share: float
    searches: list[SearchOutcome]
    roi: str = "priors"
    defer: tuple[float, ...] = ()
    per_image: dict = field(default_factory=dict)

    @property
    def n1(self) -> int:
        return len(self.split.d1)

    @property
    def n2(self) -> int:
        return len(self.split.d2)

    @property
    def certified(self) -> bool:
        """Whether the design's own space certified a matrix."""
        return self.searches[0].chosen is not None

    def write(self, results: EvalResults) -> Section:
        req, out, own = self.requirements, results.output_dir, self.searches[0]
        record = {
            "constraints": list(req.texts),
            "alphas": list(req.alphas),
            "objective": req.objective_text,
            "maximize": req.maximize,
            "delta": self.delta,
            "guarantee": self.guarantee(),
            "split": self.split.record(),
            "search_pixels": {
                "constraints": "every pixel that can change a constraint's per-image loss "
                "under some candidate (docs/definitions.md §20)",
                "objective": self.share,
            },
            "certified_for": self.certified_for(results),
            "seed": self.split.seed,
            "searches": [s.record(req, self.n1, self.n2) for s in self.searches],
            "reported": _reported(results, req, self.per_image),
        }
        if own.chosen is not None:
            matrix = own.candidates.matrices[own.chosen]
            header = self.header(own, record["certified_for"])
            save_cost(out / "designed_cost.yaml", matrix, DESIGNED, header=header)
            record["cost_file"] = "designed_cost.yaml"
        write_json(out / "design.json", record)
        write_csv(out / "design_candidates.csv", self._rows())
        return Section(
            json={"design": record},
            table=self._table(record),
            console=self.console(),
            jobs=[("evaluation", self._figures(results))],
        )

    def console(self) -> list[str]:
        req, lines = self.requirements, []
        for s in self.searches:
            name = f"design, {s.candidates.space} space{'' if s.designed else ' (to compare)'}"
            lines.append(f"{name}: " + s.line(req, self.delta, self.n2))
            if s.designed and s.chosen is not None:
                lines += [f"{name}: {note}" for note in s.notes(req)]
        if self.changes():
            lines.append(f"design: {self.changes()}")
        images = self.searches[0].images(req)
        if images:
            lines.append(
                "design: images with a defined loss (search of "
                f"{self.n1}, certification of {self.n2}): "
                + "; ".join(f"{t} {v['search']}, {v['certification']}" for t, v in images.items())
            )
        return lines

    def changes(self) -> str:
        """The share of labelled held-out pixels each search's chosen (else best) matrix decides
        otherwise than argmax, in words ("" with a single search)."""
        shown = [s for s in self.searches if s.changed is not None]
        if len(self.searches) < 2 or not shown:
            return ""
        return "labelled held-out pixels decided otherwise than argmax: " + ", ".join(
            f"{s.candidates.space} {_share(s.changed)}"
            + ("" if s.chosen is not None else " (not certified)")
            for s in shown
        )

    def guarantee(self) -> str:
        """What the certificate says, in words."""
        return (
            f"With probability at least {1 - self.delta:g} (δ = {self.delta:g}) over the draw "
            f"of the {self.n2} certification images, the matrix meets every requirement at once, "
            "each requirement bounding a mean over images of that image's own loss (for a "
            "rate such as recall: 1 − the image's recall, over the images where it is "
            "defined) on new images drawn like the held-out ones, seen by the same network "
            "with the same RoI map. It bounds neither the pooled pixel rate nor any one image: "
            "table.md shows both beside the mean."
        )

    def certified_for(self, results: EvalResults) -> dict:
        """What the certificate holds for: the probability source (a file's SHA-256), the
        held-out images, the RoI map."""
        return {
            "source": fingerprint(results.source),
            "held_out": self.split.held_out,
            "roi_map": f"--roi {self.roi}",
            "priors": _priors_words(results.source.get("priors")),
        }

    def header(self, own: SearchOutcome, certified_for: dict) -> str:
        req, t, k = self.requirements, own.testing, own.chosen
        lines = [
            f"designed by costseg evaluate.py --design {own.candidates.space} "
            f"(docs/definitions.md §20{', §21' if own.candidates.space == 'regional' else ''})",
            "guarantee: " + self.guarantee(),
        ]
        for i, (text, target) in enumerate(zip(req.texts, req.constraints, strict=True)):
            lines.append(
                f"{REQUIREMENT}{text}: mean per-image {_loss_words(target)} <= "
                f"{req.alphas[i]:.3g}; certification risk {t.risks_d2[k, i]:.4f} on "
                f"{t.n_d2[k, i]} of {self.n2} images (p = {t.pvalues_d2[k, i]:.3g}), search "
                f"risk {t.risks_d1[k, i]:.4f} on {t.n_d1[k, i]} of {self.n1}"
            )
        lines += [
            f"{CERTIFIED_FOR}{certified_for['source']}; held-out images "
            f"{certified_for['held_out']}, split at random with --seed {self.split.seed} "
            f"({self.n1} search, {self.n2} certification; design.json lists them); RoI map "
            f"{certified_for['roi_map']} (priors: {certified_for['priors']})",
            f"search: {own.candidates.space} space, {own.candidates.how}; "
            f"{len(own.candidates.objective)} candidates, front {len(t.front)}, certified "
            f"{len(t.certified)}; chosen {_parameters(own.candidates, k)}; objective "
            f"{req.objective_text} = {own.objective_all[k]:.4f} on the held-out images",
        ]
        if own.deferred is not None:
            lines.append(f"defers {_share(own.deferred['all pixels'])} of the labelled "
                         "held-out pixels")  # fmt: skip
        if own.candidates.space == "regional":
            moved = ", ".join(
                f"{t} moves {roi_label(c.roi)}"
                for t, c in zip(req.texts, req.constraints, strict=True)
            )
            lines.append(f"regions (docs/definitions.md §21): {moved}; every other region keeps "
                         "C0, decided with the RoI map above")  # fmt: skip
        wrapped = [
            textwrap.fill(
                line, 98, subsequent_indent="  ", break_long_words=False, break_on_hyphens=False
            )
            for line in lines
        ]
        return "\n".join(wrapped)

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
                    f"certification risk {text}": t.risks_d2[k, i]
                    for i, text in enumerate(req.texts)
                }
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
            f"## Designed value system (δ = {self.delta}; {self.split.held_out}, split at "
            f"random with seed {self.split.seed}: search on {self.n1} images, certification "
            f"on {self.n2})",
            "",
            self.guarantee(),
            "",
            "| space | search | candidates | front | certified | chosen | "
            + " | ".join(f"{t} (certification risk; images)" for t in req.texts)
            + f" | {req.objective_text} (held-out) |",
            "|---" * (6 + len(req.texts) + 1) + "|",
        ]
        for s in self.searches:
            c, t, k = s.candidates, s.testing, s.chosen
            cells = [c.space, c.how, len(c.objective), len(t.front), len(t.certified)]
            if k is None:
                cells += ["none"]
                cells += [f"– ({n2} of {self.n2})" for n2 in _images_of(t, t.best, len(req.texts))]
                cells += ["–"]
            else:
                cells += [_parameters(c, k)]
                cells += [f"{r:.4f} ({n} of {self.n2})" for r, n in zip(t.risks_d2[k], t.n_d2[k],
                                                                         strict=True)]  # fmt: skip
                cells += [f"{s.objective_all[k]:.4f}"]
            lines.append("| " + " | ".join(map(str, cells)) + " |")
        for s in self.searches:
            for note in s.notes(req) if s.designed and s.chosen is not None else []:
                lines += ["", f"Note: {note}."]
            if s.chosen is None and s.testing.best is not None:
                lines += ["", f"{s.candidates.space}: {s.why(req)}."]
            if s.deferred is not None:
                shares = ", ".join(f"{k} {_share(v)}" for k, v in s.deferred.items())
                lines += ["", f"{s.candidates.space}: deferred share of labelled held-out "
                          f"pixels: {shares}."]  # fmt: skip
        if self.changes():
            lines += ["", f"Pixels changed: {self.changes()}."]
        lines += _reported_table(record["reported"])
        return "\n".join(lines) + "\n"

    def _figures(self, results: EvalResults):
        from costseg.report.results import figure_subject

        req, own = self.requirements, self.searches[0]
        matrices = []
        if own.chosen is not None:
            matrices = [
                *shown_matrices(DESIGNED, own.candidates.matrices[own.chosen]),
                ("robotistic", load_cost("robotistic")),
            ]
        fronts = []
        for s in self.searches:
            t = s.testing
            arguments = (t.risks_d1, s.candidates.objective, t.front, t.certified, s.chosen,
                         list(req.texts), list(req.alphas), req.objective_text)  # fmt: skip
            fronts.append((s.candidates.space, arguments, (t.risks_d2, t.order)))
        title = f"designed value system, {figure_subject(results.source, [])}"
        return job(design_figures, matrices, list(CLASS_NAMES), fronts, title)


def _edge_note(values: np.ndarray, k: int, i: int, text: str, grid: bool) -> list[str]:
    """A note when candidate k's multiplier ``values[k]`` lies at an edge of the (L,) values
    searched (on a ``grid``, or continuously): the largest, or the smallest above 0."""
    tried = values[values > 0]
    if not len(tried) or values[k] <= 0 or tried.min() == tried.max():
        return []
    if values[k] >= tried.max():
        return [f"μ_{i + 1} ({text}) is {values[k]:g}, the top of the values searched: the "
                "space may hold a better matrix beyond it"]  # fmt: skip
    if values[k] <= tried.min():
        between = " (--design_search continuous searches between the grid's values)"
        return [f"μ_{i + 1} ({text}) is {values[k]:g}, the smallest value searched above 0: a "
                f"smaller multiplier may do better{between if grid else ''}"]  # fmt: skip
    return []


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


def shown_matrices(name: str, cost: torch.Tensor) -> list[tuple[str, torch.Tensor]]:
    """The matrices a figure shows of ``cost``: itself; of a regional stack, the default and
    each RoI's matrix that differs from it.

    >>> stack = torch.stack([torch.eye(2)] * 2 + [2 * torch.eye(2)] * 3)
    >>> [n for n, _ in shown_matrices("d", stack)]
    ['d (default)', 'd, RoI 2 (sidewalk)', 'd, RoI 3 (building)', 'd, RoI 4 (sky)']
    """
    if not is_regional(cost):
        return [(name, cost)]
    return [(f"{name} (default)", cost[0])] + [
        (f"{name}, {roi_label(r)}", m)
        for r, m in enumerate(cost)
        if r and not torch.equal(m, cost[0])
    ]


def _risks(values) -> str:
    return ", ".join("undefined" if math.isnan(r) else f"{r:.3f}" for r in np.asarray(values))


def _counts(values) -> str:
    return ", ".join(str(int(n)) for n in np.asarray(values))


def _share(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def _images_of(t: ParetoTestingResult, k: int | None, count: int) -> list[int]:
    return [0] * count if k is None else [int(n) for n in t.n_d2[k]]


def _where(target: Target) -> str:
    """Which images define a constraint's loss, in words."""
    cls = "any class" if target.cls is None else CLASS_NAMES[target.cls]
    region = "the image" if target.roi == 0 else f"RoI {target.roi} ({ROI_NAMES[target.roi]})"
    if target.metric in ("precision", "fp_rate"):
        return f"has a pixel decided {cls} in {region}"
    return f"holds {cls} in {region}"


def _loss_words(target: Target) -> str:
    """The per-image loss of a constraint, in words."""
    if target.metric in SEGMENT_RATES:
        return f"{target.metric} (over the images where it is defined)"
    what = "instance recall" if target.metric in INSTANCE_RATES else target.metric
    return f"(1 − {what}) (over the images where it is defined)"


def _defer_hint(target: Target, defers: bool) -> str:
    if defers and target.metric == "recall":
        return (
            "; a deferred pixel counts as a miss of recall: a deferring design can meet "
            "handled_recall (deferred pixels count as handled)"
        )
    return ""


def _priors_words(record) -> str:
    """The priors behind the RoI map, short (their record without its notes)."""
    if isinstance(record, dict):
        return ", ".join(f"{k} {v}" for k, v in record.items() if k != "note")
    return "none" if record is None else str(record)


def _reported(results: EvalResults, req: Requirements, per_image: dict) -> dict:
    """Per constraint and rule (the named rules and the designed ones), on the reported images:
    the pooled rate (every image's pixels or segments counted together), the mean per-image
    loss (what the certificate bounds), the images where that loss is defined, and how many of
    them miss the requirement's level on their own; and each rule's mIoU (``miou``)."""
    designed = next((g for g in results.groups if g.group.family == DESIGNED_FAMILY), None)
    named = named_group([g.group for g in results.groups])
    groups = [results.result_of(named)] + ([designed] if designed is not None else [])
    out = {
        "miou": {
            name: g.pixels["miou"][k].item() if "miou" in g.pixels else None
            for g in groups
            for k, name in enumerate(g.group.names)
        }
    }
    for text, target in zip(req.texts, req.constraints, strict=True):
        out[text] = {}
        for g in groups:
            try:
                values = metric_values(g.pixels, g.segments, target, results.class_ids,
                                       g.instances)  # fmt: skip
            except (ValueError, KeyError, IndexError):  # a rate not measured on these images
                values = torch.full((len(g.group.names),), math.nan)
            for name, value in zip(g.group.names, values.tolist(), strict=True):
                mine = per_image.get(text, {}).get(name, {})
                out[text][name] = {
                    "pooled": value,
                    "mean_per_image_risk": mine.get("risk"),
                    "images": mine.get("images"),
                    "images_above_alpha": mine.get("above_alpha"),
                }
    return out


def _reported_table(reported: dict) -> list[str]:
    reported = dict(reported)
    miou = reported.pop("miou", {})
    if not reported:
        return []
    rules = list(next(iter(reported.values())))
    lines = [
        "",
        "On the reported images, per requirement and rule: the pooled rate (all images' pixels "
        "or segments together), the mean per-image risk (what the certificate bounds) and the "
        "images that miss the requirement on their own:",
        "",
        "| requirement | " + " | ".join(rules) + " |",
        "|---" * (len(rules) + 1) + "|",
    ]
    for text, values in reported.items():
        cells = []
        for v in values.values():
            pooled = "–" if v["pooled"] is None or math.isnan(v["pooled"]) else f"{v['pooled']:.4f}"
            risk = v["mean_per_image_risk"]
            if risk is None:
                cells.append(f"{pooled} pooled")
            else:
                cells.append(f"{pooled} pooled, risk {risk:.4f}, {v['images_above_alpha']} of "
                             f"{v['images']} images miss")  # fmt: skip
        lines.append(f"| {text} | " + " | ".join(cells) + " |")
    if miou:
        values = [miou.get(rule) for rule in rules]
        lines.append("| mIoU | " + " | ".join("–" if v is None else f"{100 * v:.2f}"
                                                for v in values) + " |")  # fmt: skip
    return lines
