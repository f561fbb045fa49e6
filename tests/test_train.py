"""`python train.py` end to end: fit, checkpoint, reload, resume, foreign checkpoints."""

from pathlib import Path

import pytest
import torch
import yaml
from conftest import TINY_TRAIN
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.cli import train_main
from costseg.data.toy import StreetScenes
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.training.module import SegmentationModule

pytestmark = pytest.mark.e2e  # trainings


def _last(runs: Path) -> Path:
    return find_checkpoint(None, runs_dir=runs)


def test_fast_dev_run_through_the_entry_point(tmp_path):
    module, trainer = train_main(
        [
            *TINY_TRAIN,
            "--trainer.fast_dev_run=true",
            f"--trainer.default_root_dir={tmp_path}",
            f"--trainer.logger.init_args.save_dir={tmp_path}",
        ]
    )
    assert trainer.global_step == 1
    assert module.priors.shape == (19, 64, 128)
    assert torch.allclose(module.priors.sum(0), torch.ones(64, 128))


def test_run_folder_holds_checkpoints_priors_and_figures(tiny_run):
    _, trainer, runs = tiny_run
    run = Path(trainer.log_dir)
    for name in ("priors.pt", "priors.png", "roi_map.png", "config.yaml", "checkpoints/last.ckpt"):
        assert (run / name).is_file(), name
    assert _last(runs).parent == run / "checkpoints"


def test_run_folder_config_and_priors_match_the_trained_module(tiny_run):
    module, trainer, _ = tiny_run
    run = Path(trainer.log_dir)
    config = yaml.safe_load((run / "config.yaml").read_text())
    hparams = {k: v for k, v in module.hparams.items() if not k.startswith("_")}
    # the network's num_classes is linked to the model's, and recorded in the checkpoint
    config["model"]["net"]["init_args"]["num_classes"] = config["model"]["num_classes"]
    config["model"]["loss"].setdefault("init_args", {})
    assert config["model"] == hparams
    saved = torch.load(run / "priors.pt", map_location="cpu", weights_only=True)
    assert saved["class_names"] == list(CLASS_NAMES)
    assert torch.equal(saved["priors"], module.priors)


def test_last_checkpoint_weights_rebuild_the_trained_network(tiny_run):
    module, trainer, runs = tiny_run
    config = yaml.safe_load((Path(trainer.log_dir) / "config.yaml").read_text())["model"]
    assert config["net"]["class_path"] == "costseg.models.deeplabv3plus.DeepLabV3Plus"
    fresh = DeepLabV3Plus(config["num_classes"], **config["net"]["init_args"])
    if config["channels_last"]:  # the trained network's memory format: the same kernels run
        fresh = fresh.to(memory_format=torch.channels_last)
    state = torch.load(_last(runs), map_location="cpu", weights_only=True)
    fresh.load_state_dict(
        {k.removeprefix("net."): v for k, v in state["state_dict"].items() if k.startswith("net.")}
    )
    x = torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(0))
    module.eval(), fresh.eval()
    with torch.no_grad():
        assert torch.equal(fresh(x), module.net(x))


def test_event_file_holds_the_validation_scalars_the_trainer_reports(tiny_run):
    _, trainer, _ = tiny_run
    acc = EventAccumulator(trainer.log_dir).Reload()
    reported = {k: v.item() for k, v in trainer.logged_metrics.items() if k.startswith("val/")}
    assert sorted(acc.Tags()["scalars"]) == sorted(reported)
    logged = {tag: [e.value for e in acc.Scalars(tag)] for tag in reported}
    # One validation, at the last step; NaN (an empty class) is logged as NaN.
    torch.testing.assert_close(
        torch.tensor([logged[tag] for tag in reported]),
        torch.tensor([[v] for v in reported.values()]),
        rtol=0,
        atol=0,
        equal_nan=True,
    )


def test_checkpoint_reload_gives_identical_predictions(tiny_run):
    module, _, runs = tiny_run
    loaded = SegmentationModule.load_from_checkpoint(_last(runs), map_location="cpu")
    images = torch.stack([StreetScenes("val", 2, (64, 128))[i][0] for i in range(2)])
    module.eval(), loaded.eval()
    with torch.no_grad():
        assert torch.equal(module(images), loaded(images))
    assert torch.equal(module.priors, loaded.priors)
    assert loaded.data_config["class_path"].endswith("StreetScenesDataModule")


def test_resume_continues_the_step_count(tiny_run, tmp_path):
    _, _, runs = tiny_run
    _, trainer = train_main(
        [
            *TINY_TRAIN,
            "--trainer.max_steps=4",
            f"--trainer.logger.init_args.save_dir={tmp_path}",
            f"--ckpt_path={_last(runs)}",
        ]
    )
    assert trainer.global_step == 4


def test_checkpoint_of_another_class_set_is_refused(tiny_run, tmp_path, capsys):
    _, _, runs = tiny_run
    checkpoint = torch.load(_last(runs), map_location="cpu", weights_only=False)
    checkpoint["costseg"]["class_names"] = ["road", "car", "person"]
    foreign = tmp_path / "foreign.ckpt"
    torch.save(checkpoint, foreign)
    with pytest.raises(SystemExit) as exit_info:
        train_main(
            [
                *TINY_TRAIN,
                f"--trainer.logger.init_args.save_dir={tmp_path}",
                f"--ckpt_path={foreign}",
            ]
        )
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "trained on 3 classes" in err[0] and "19 classes are expected" in err[0]


def test_missing_resume_checkpoint(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_main([*TINY_TRAIN, f"--ckpt_path={tmp_path / 'nope.ckpt'}"])
    assert exit_info.value.code == 2
    assert "checkpoint not found" in capsys.readouterr().err


def test_a_loss_recipe_trains_logs_its_terms_and_is_recorded(tmp_path):
    """configs/losses/ composes with a recipe; TensorBoard holds the loss's terms, which add up
    to the loss, and evaluation reads the loss back from the checkpoint."""
    module, trainer = train_main(
        [
            "--config",
            "toy",
            "--config",
            "losses/expected_cost_altruistic",
            *TINY_TRAIN,
            "--model.loss.init_args.lam=0.5",
            "--trainer.log_every_n_steps=1",
            f"--trainer.logger.init_args.save_dir={tmp_path}",
        ]
    )
    assert Path(trainer.log_dir).parent.name == "toy_expected_cost_altruistic"
    acc = EventAccumulator(trainer.log_dir).Reload()
    logged = {t: acc.Scalars(t)[-1].value for t in ("train/loss", "train/cross_entropy")}
    expected_cost = acc.Scalars("train/expected_cost")[-1].value
    assert expected_cost > 0
    assert logged["train/loss"] == pytest.approx(
        logged["train/cross_entropy"] + 0.5 * expected_cost
    )
    entry = {
        "class_path": "costseg.training.losses.ExpectedCostCrossEntropy",
        "init_args": {"cost": "altruistic", "lam": 0.5},
    }
    assert module.hparams["loss"] == entry
    from costseg.networks import load_costseg_checkpoint

    assert load_costseg_checkpoint(_last(tmp_path)).hparams["loss"] == entry


def test_priors_are_counted_once_per_dataset_whatever_the_save_dir(tmp_path, capsys):
    """A second run on the same labels under another save_dir (and another batch size, which
    does not change the labels) reads the priors the first one counted; other labels (another
    prior_images) are counted anew. The reference: the pixel priors counted here directly."""
    from costseg.data.datamodule import StreetScenesDataModule
    from costseg.data.priors import count_pixel_priors, read_priors_file

    one_step = [*TINY_TRAIN, "--trainer.max_steps=1", "--trainer.limit_val_batches=0"]
    runs = {}
    for name, extra in (("a", []), ("b", ["--data.init_args.batch_size=4"]),
                        ("c", ["--data.init_args.prior_images=3"])):  # fmt: skip
        _, trainer = train_main(
            [*one_step, *extra, f"--trainer.logger.init_args.save_dir={tmp_path / name}"]
        )
        runs[name] = read_priors_file(Path(trainer.log_dir) / "priors.pt", CLASS_NAMES)["priors"]
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("priors ")]
    assert [line.split()[1] for line in lines] == ["computed", "reused", "computed"], lines
    assert len(list((tmp_path / "priors_cache").glob("*.pt"))) == 2
    data = StreetScenesDataModule(batch_size=2, num_workers=0, size=(64, 128), prior_images=4)
    expected = count_pixel_priors(data.prior_labels(), 19, None, 1e-5, False, None)[0]
    assert torch.equal(runs["a"], expected) and torch.equal(runs["b"], expected)
    assert not torch.equal(runs["c"], expected)
