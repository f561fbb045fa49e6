"""What a design says when nothing is certified, and why (docs/definitions.md §20): an undefined
certification risk is not a risk above α, a requirement no candidate meets even on the search
images is said to be out of the space's reach, and a deferring design's recall is flagged."""

from __future__ import annotations

import textwrap

import numpy as np
import torch

from costseg.calibration.design_search import Candidates
from costseg.calibration.pareto_testing import pareto_testing
from costseg.metrics.requirements import Requirements
from costseg.report.design import SearchOutcome

REQUIRE = ["person:roi1:recall>=0.8", "rider:roi1:recall>=0.5"]


def _outcome(d1: np.ndarray, d2: np.ndarray, defers: bool = False) -> SearchOutcome:
    length = d1.shape[1]
    candidates = Candidates(
        "lagrangian", ("mu_1", "mu_2"), np.zeros((length, 2)), torch.zeros(length, 19, 19),
        np.linspace(0.9, 0.8, length),
    )  # fmt: skip
    req = Requirements.parse(REQUIRE)
    result = pareto_testing(d1, d2, req.alphas, 0.1, candidates.objective)
    assert result.certified.size == 0 and result.best is not None
    deferred = {"all pixels": 0.2} if defers else None
    return SearchOutcome(candidates, result, None, np.full(length, np.nan), deferred=deferred)


def test_an_undefined_certification_risk_is_not_a_risk_above_alpha() -> None:
    d1 = np.zeros((40, 3, 2))
    d1[::2, :, 1] = np.nan  # rider in the street on half of the search images
    d2 = np.zeros((40, 3, 2))
    d2[:, :, 1] = np.nan  # and on no certification image
    found = _outcome(d1, d2)
    req = Requirements.parse(REQUIRE)
    why = found.why(req)
    assert REQUIRE[1] in why and "undefined" in why and "more images would help" in why
    assert "would not help" not in why and "above α:" not in why
    assert found.testing.needed_images is not None  # at the search images' share of riders
    line = found.line(req, 0.1, 40)
    assert "certification risks 0.000, undefined" in line and "on 40, 0 of 40 images" in line
    assert found.images(req)[REQUIRE[1]] == {"search": 20, "certification": 0}


def test_a_requirement_no_candidate_meets_on_the_search_images_is_out_of_reach() -> None:
    d1 = np.zeros((40, 3, 2))
    d1[:, :, 0] = 0.5  # every candidate misses half of each image's persons: α is 0.2
    found = _outcome(d1, d1.copy(), defers=True)
    req = Requirements.parse(REQUIRE)
    why = found.why(req)
    assert "no candidate of the space meets person:roi1:recall>=0.8" in why
    assert "cannot reach it" in why and "handled_recall" in why
    assert any("handled_recall" in note for note in found.notes(req))


def test_a_designed_file_used_with_another_network_is_noted(tmp_path) -> None:
    from costseg.report.certified import CERTIFIED_FOR, certificate_notes, fingerprint

    ours, other = tmp_path / "ours.ckpt", tmp_path / "other.ckpt"
    ours.write_bytes(b"weights")
    other.write_bytes(b"other weights")
    made_with = fingerprint({"network": f"costseg:{ours}"})
    cost = tmp_path / "designed_cost.yaml"
    line = f"{CERTIFIED_FOR}{made_with}; held-out ..."
    wrapped = textwrap.fill(
        line, 40, subsequent_indent="  ", break_long_words=False, break_on_hyphens=False
    ).replace("\n", "\n# ")
    cost.write_text(f"# designed by costseg\n# {wrapped}\nname: d\n")  # as the header wraps
    moved = tmp_path / "moved.ckpt"
    moved.write_bytes(b"weights")  # the same file elsewhere: the same certificate
    assert certificate_notes([str(cost)], {"network": f"costseg:{moved}"}) == []
    (note,) = certificate_notes([str(cost), "robotistic"], {"network": f"costseg:{other}"})
    assert note.startswith(f"note: {cost} was certified for {made_with}") and "other.ckpt" in note


def test_a_multiplier_at_an_edge_of_the_values_searched_is_noted() -> None:
    """μ at the top of the values searched, or at the smallest above 0, gets a note (the
    console, table.md and design.json show a search's notes); one inside gets none."""
    req = Requirements.parse(REQUIRE)
    d1 = np.full((40, 4, 2), 0.6)  # nothing certified; the notes are the shown candidate's
    found = _outcome(d1, d1.copy())
    mu = np.array([[0.0, 0.0], [0.01, 1.0], [1.0, 100.0], [100.0, 0.1]])
    found.candidates = Candidates("regional", ("mu_1", "mu_2"), mu, torch.zeros(4, 5, 19, 19),
                                  np.zeros(4))  # fmt: skip
    smallest = "μ_1 (person:roi1:recall>=0.8) is 0.01, the smallest"
    top = "μ_2 (rider:roi1:recall>=0.5) is 100, the top"
    for chosen, want in ((1, [smallest]), (2, [top]), (0, [])):
        found.chosen = chosen
        notes = found.notes(req)
        assert [n[: len(w)] for n, w in zip(notes, want, strict=True)] == want, notes
