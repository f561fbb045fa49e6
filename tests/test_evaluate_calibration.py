"""`evaluate.py --calibrate / --temperature_sweep / --guarantee` end to end on a tiny model."""

import json
from collections import Counter

import pytest

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.networks.sources import Source


@pytest.fixture(scope="module")
def ckpt(tiny_run):
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


@pytest.mark.figures
def test_temperature_scaling_and_sweep(ckpt, tmp_path):
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "egoistic", "--calibrate", "temperature"]
    results = evaluate_main(
        [*args, "--temperature_sweep", "--output_dir", str(out), "--no-progress"]
    )
    # The first half (1 of 3 images) fits, the other two are reported.
    assert results.num_images == 2
    record = json.loads((out / "calibration.json").read_text())
    fitted = record["scaling"]["temperature"]
    assert record["scaling"]["kind"] == "temperature" and fitted > 0
    assert "1 images" in record["scaling"]["fitted_on"]
    assert set(record["ece"]) == {"raw", "scaled"}
    csv = (out / "calibration.csv").read_text().splitlines()
    assert csv[0].startswith("probabilities,ece,classwise_ece,nll,brier,ece_road,")
    assert [line.split(",")[0] for line in csv[1:]] == ["raw", "scaled"]
    # Temperature scaling minimises the NLL of the fitted half; on these scenes the reported
    # half gains too.
    assert record["nll"]["scaled"] < record["nll"]["raw"]
    assert f"T = {fitted:.3f}" in (out / "table.md").read_text()
    rows = json.loads((out / "temperature_sweep.json").read_text())["rows"]
    temps = sorted({r["temperature"] for r in rows})
    assert temps == sorted({0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, fitted})
    # Argmax does not move with T: every robotistic row is the same at every temperature.
    robotistic = {}
    for r in rows:
        if r["matrix"] == "robotistic":
            key = (r["class"], r["roi"])
            value = (r["precision"], r["recall"], r["miou"])
            assert robotistic.setdefault(key, value) == value
    assert (out / "figures" / "reliability.png").is_file()
    assert (out / "figures" / "temperature_person.png").is_file()


def test_guarantee_on_a_disjoint_calibration_split(ckpt, tmp_path, capsys, monkeypatch):
    """Learn-then-Test on the train split; with --calibrate, --meta and --conformal, which fit
    on the same held-out images, every image goes through the network once."""
    seen, original = Counter(), Source.scores

    def counted(self, images, stems, *args, **kwargs):  # scores_and_entropy calls it too
        seen.update(stems)
        return original(self, images, stems, *args, **kwargs)

    monkeypatch.setattr(Source, "scores", counted)
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "--sweep", "0.5", "--no-progress"]
    args += ["--target", "person:roi0:recall>=0.5", "--maximize", "person:roi0:precision"]
    args += ["--calibrate", "temperature", "--meta", "--conformal", "0.3"]
    evaluate_main(
        [*args, "--guarantee", "0.5", "--calibration_split", "train", "--output_dir", str(out)]
    )
    assert len(seen) == 8 + 3 and set(seen.values()) == {1}  # train held out, val reported
    record = json.loads((out / "guarantee.json").read_text())
    assert record["calibration_images"] == 8 and record["candidates"] == 6
    assert record["alpha"] == pytest.approx(0.5) and record["delta"] == 0.5
    printed = capsys.readouterr().out
    if record["found"]:
        assert record["chosen"] in record["certified"]
        assert record["pvalue"] <= 0.5 / 6  # Bonferroni over the 6 grid points
        assert record["images_used"] + record["images_left_out"] == 8
        assert "certified for person:roi0:recall>=0.5" in printed
    else:
        assert record["certified"] == [] and "no value system is certified" in printed
