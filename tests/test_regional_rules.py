"""A regional value system as one more rule (docs/definitions.md §21): evaluate.py and predict.py
with configs/costs/street_person.yaml on the tiny checkpoint, the saved label maps against a loop
over the RoIs that calls ``decide_reference`` with each RoI's matrix on the saved probabilities,
the rows of results.json, and the refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import costseg
from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, LABEL_ID_TO_TRAIN_ID, ROI_NAMES
from costseg.cli import predict_main
from costseg.costs import COSTS_DIR, load_cost, symmetric_cost
from costseg.data.priors import roi_map
from costseg.data.toy import StreetScenes
from costseg.decision import decide_reference
from costseg.meta.fusion import fusion_group
from costseg.networks import load_costseg_checkpoint, load_network
from costseg.networks.probs_files import load_probs
from costseg.rules import (
    Rule,
    alpha_group,
    parse_rules,
    require_roi,
    rules_group,
    vertex_matrices,
)

STREET = str(COSTS_DIR / "street_person.yaml")
PERSON = CLASS_NAMES.index("person")


def loop_over_rois(probs: torch.Tensor, stack: torch.Tensor, roi: torch.Tensor) -> np.ndarray:
    """(H, W): each RoI's pixels decided by ``decide_reference`` with that RoI's matrix."""
    out = np.full(roi.shape, -1)
    for r in range(len(stack)):
        mine = (roi == r).numpy()
        out[mine] = decide_reference(probs[None], stack[r])[0].numpy()[mine]
    return out


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> Path:
    return find_checkpoint(None, runs_dir=tiny_run[2])


@pytest.fixture(scope="module")
def network(ckpt):
    return load_network(f"costseg:{ckpt}")


@pytest.fixture(scope="module")
def evaluated(ckpt, network, tmp_path_factory):
    """The Python API on two procedural scenes with the checkpoint's priors (the RoI map)."""
    out = tmp_path_factory.mktemp("regional")
    results = costseg.evaluate(
        network, StreetScenes("val", length=2, size=(64, 128)), ["robotistic", STREET],
        priors=load_costseg_checkpoint(ckpt).priors, output_dir=str(out), num_examples=2,
        save_probs=True, save_predictions=True, progress=False,
    )  # fmt: skip
    return results, out


def _saved(out: Path, rule: str, stem: str) -> np.ndarray:
    return LABEL_ID_TO_TRAIN_ID[np.array(Image.open(out / "predictions" / rule / f"{stem}.png"))]


def test_evaluate_decides_each_roi_with_its_matrix_and_reports_it_as_a_rule(evaluated):
    results, out = evaluated
    stack = load_cost(STREET)
    roi = results.roi
    stems = [ex.name for ex in results.examples]
    assert len(stems) == 2
    changed = 0
    for stem in stems:
        probs = load_probs(out / "probs" / f"{stem}.npz")
        assert roi.shape == probs.shape[1:]
        regional, plain = _saved(out, "street_person", stem), _saved(out, "robotistic", stem)
        assert (regional == loop_over_rois(probs, stack, roi)).all()
        off_street = (roi != 1).numpy()
        assert (regional[off_street] == plain[off_street]).all()  # the default: argmax
        changed += int((regional != plain).sum())
    record = json.loads((out / "results.json").read_text())
    rows = {(r["matrix"], r["class"], r["roi"]) for r in record["rows"]}
    for cls in ("person", "building"):
        for r in range(len(ROI_NAMES)):
            assert ("street_person", cls, r) in rows and ("robotistic", cls, r) in rows
    assert "defer" not in record  # neither rule defers
    street = {r["matrix"]: r for r in record["rows"] if r["class"] == "person" and r["roi"] == 1}
    if changed:  # more person pixels in the street: recall can only rise
        assert street["street_person"]["recall"] >= street["robotistic"]["recall"]


def test_predict_decides_with_the_roi_map_it_writes(ckpt, tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    image = np.random.default_rng(0).integers(0, 256, (40, 72, 3), dtype=np.uint8)
    Image.fromarray(image).save(folder / "a.png")
    out = tmp_path / "out"
    predict_main(["--input", str(folder), "--ckpt_path", str(ckpt), "--output_dir", str(out),
                  "--save-probs", "--cost", STREET, "--no-progress"])  # fmt: skip
    assert (out / "roi_map.png").is_file()
    counts = json.loads((out / "counts.json").read_text())
    assert "priors of the network's checkpoint" in counts["roi_map"]
    probs = load_probs(out / "probs" / "a.npz")
    priors = torch.nn.functional.interpolate(
        load_costseg_checkpoint(ckpt).priors[None].double(), size=(40, 72), mode="bilinear"
    )[0]
    expected = loop_over_rois(probs, load_cost(STREET), roi_map(priors / priors.sum(0)))
    labels = LABEL_ID_TO_TRAIN_ID[np.array(Image.open(out / "labels" / "street_person" / "a.png"))]
    assert (labels == expected).all()


def test_the_api_without_a_roi_map_refuses_before_the_first_image(network, tmp_path):
    with pytest.raises(
        ValueError, match=r'the given dataset: pass priors= .* or roi="geometric"'
    ) as err:
        costseg.evaluate(network, StreetScenes("val", length=2, size=(64, 128)), [STREET],
                         output_dir=str(tmp_path / "none"), progress=False)  # fmt: skip
    assert "\n" not in str(err.value)
    assert not (tmp_path / "none" / "results.json").exists()


def test_a_regional_rule_without_a_roi_map_is_refused_in_one_line():
    group = rules_group(parse_rules([STREET]))
    assert group.needs_roi and group.rules[0].regional
    require_roi([group], torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"street_person decides each RoI with its own matrix.*"):
        require_roi([group], None, "pass --roi geometric")
    require_roi([rules_group(parse_rules(["egoistic"]))], None)  # a plain rule needs none


def test_where_one_matrix_is_needed_a_regional_file_is_refused():
    with pytest.raises(ValueError, match="a vertex of the triangle takes one matrix; street_"):
        vertex_matrices(["robotistic", "altruistic", STREET])
    with pytest.raises(ValueError, match="--alpha_cost takes one matrix"):
        alpha_group(0.5, STREET)
    with pytest.raises(ValueError, match="--fuse takes one matrix"):
        fusion_group(parse_rules(["robotistic"])[0], parse_rules([STREET]), [0.5], [PERSON])


def test_a_regional_rule_with_defer_gets_a_row_in_every_matrix():
    rule = parse_rules([STREET], defer=0.25)[0]
    assert rule.regional and rule.defers and rule.defer_cost == 0.25
    assert rule.cost.shape == (5, 20, 19)
    own = Rule("x", torch.stack([symmetric_cost(2)] * 5))
    assert not own.defers and own.defer_cost is None


def test_the_defer_sweep_of_a_regional_rule_decides_each_roi_with_its_row():
    from costseg.rules import defer_group

    group = defer_group([STREET], [0.0, 0.4])
    assert group.needs_roi and [r.defer_cost for r in group.rules] == [0.0, 0.4]
    probs = torch.rand(1, 19, 6, 8, generator=torch.Generator().manual_seed(0)).softmax(1)
    roi = torch.arange(48).view(6, 8) % 5
    stack = load_cost(STREET)
    for k, c in enumerate((0.0, 0.4)):
        deferring = torch.cat([stack, torch.full((5, 1, 19), c, dtype=torch.float64)], 1)
        expected = loop_over_rois(probs[0], deferring, roi)  # 255: deferred
        assert (group.decide(probs, None, roi)[0, k].numpy() == expected).all()
