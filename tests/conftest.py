"""Shared fixtures: a small Cityscapes-layout tree written into ``tmp_path``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

CITYSCAPES_SIZE = (32, 64)
"""(H, W) of every generated Cityscapes image."""
CITYSCAPES_FILES = {
    "val": ["frankfurt_000000_000294", "frankfurt_000000_000576", "lindau_000000_000019"],
    "train": ["aachen_000000_000019", "aachen_000001_000019", "bochum_000000_000313"],
}
"""Split → item names of the generated tree, in sorted order."""
LABEL_IDS = np.array([*range(34), 255], dtype=np.uint8)
"""Every id a ``*_gtFine_labelIds.png`` may hold: 0-33 and license plate's -1 stored as 255."""


def cityscapes_label_ids(
    item: int, size: tuple[int, int] = CITYSCAPES_SIZE, valid_only: bool = False
) -> np.ndarray:
    """(H, W) uint8 label ids of generated item ``item``: 4x8 blocks cycling through LABEL_IDS
    (without 255 when ``valid_only``: the official evaluator stops at an unknown id)."""
    h, w = size
    ids_used = LABEL_IDS[:-1] if valid_only else LABEL_IDS
    block = np.arange(h // 4)[:, None] * (w // 8) + np.arange(w // 8)[None, :]
    ids = ids_used[(block + 7 * item) % len(ids_used)]
    return np.kron(ids, np.ones((4, 8), dtype=np.uint8))


def cityscapes_image(label_ids: np.ndarray) -> np.ndarray:
    """(3, H, W) uint8 image whose red channel is the label id, so pixels reveal their label."""
    return np.stack([label_ids, 255 - label_ids, np.full_like(label_ids, 100)])


def write_cityscapes_item(
    root: Path,
    split: str,
    name: str,
    item: int,
    size: tuple[int, int] = CITYSCAPES_SIZE,
    valid_only: bool = False,
) -> tuple[Path, Path]:
    """Write one (H, W) = ``size`` image/label pair in Cityscapes' layout (sizes divisible by
    (4, 8)); returns (image path, label path)."""
    city = name.split("_")[0]
    image = root / "leftImg8bit" / split / city / f"{name}_leftImg8bit.png"
    label = root / "gtFine" / split / city / f"{name}_gtFine_labelIds.png"
    image.parent.mkdir(parents=True, exist_ok=True)
    label.parent.mkdir(parents=True, exist_ok=True)
    ids = cityscapes_label_ids(item, size, valid_only)
    Image.fromarray(cityscapes_image(ids).transpose(1, 2, 0)).save(image)
    Image.fromarray(ids).save(label)
    return image, label


@pytest.fixture
def one_thread():
    """Small tensors: on a busy CPU, syncing OpenMP threads costs more than the math."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def cityscapes_root(tmp_path: Path) -> Path:
    """A Cityscapes tree (``CITYSCAPES_FILES``, ``CITYSCAPES_SIZE``) under ``tmp_path``."""
    root = tmp_path / "cityscapes"
    for split, names in CITYSCAPES_FILES.items():
        for item, name in enumerate(names):
            write_cityscapes_item(root, split, name, item)
    return root


TINY_TRAIN = [
    "--model.net.init_args.backbone=resnet18",
    "--model.net.init_args.decoder_channels=16",
    "--model.val_costs=[robotistic, ml]",
    "--data.init_args.size=[64, 128]",
    "--data.init_args.batch_size=2",
    "--data.init_args.train_length=8",
    "--data.init_args.val_length=3",
    "--data.init_args.test_length=2",
    "--data.init_args.prior_images=4",
    "--data.init_args.num_workers=0",
    "--trainer.precision=32-true",  # bf16 autocast is emulated (slow) on CPUs without bf16
    "--trainer.max_steps=2",
    "--trainer.val_check_interval=2",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
]
"""Arguments of `python train.py` for a model that trains in seconds (tests only)."""


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory):
    """A tiny model trained through `train_main` (2 steps); returns (module, trainer, runs dir)."""
    from costseg.cli import train_main

    runs = tmp_path_factory.mktemp("runs")
    module, trainer = train_main([*TINY_TRAIN, f"--trainer.logger.init_args.save_dir={runs}"])
    return module, trainer, runs


@pytest.fixture(scope="session")
def vainf(tmp_path_factory) -> tuple[torch.nn.Module, Path]:
    """A VainF ResNet-50 OS16 DeepLabv3+ with random weights (BN statistics of random images),
    in eval mode, and the checkpoint file VainF's code would write for it."""
    from costseg.networks import export_vainf_state
    from costseg.networks.vainf import vainf_deeplabv3plus

    torch.manual_seed(0)
    net = vainf_deeplabv3plus(19, "resnet50", 16)
    with torch.no_grad():
        net.train()(torch.randn(2, 3, 64, 64))  # BN statistics that depend on the input
    path = tmp_path_factory.mktemp("vainf") / "best_deeplabv3plus_resnet50_cityscapes_os16.pth"
    torch.save({"model_state": export_vainf_state(net.eval())}, path)
    return net, path


EVERY_OUTPUT = [
    ["--cost", "robotistic", "ml", "--calibrate", "temperature", "--temperature_sweep",
     "--sweep", "0.5", "--alpha_sweep", "0.5", "--defer_sweep", "0.2", "0.6", "0.2",
     "--meta", "--meta_split", "train", "--meta_images", "6", "--fuse", "ml", "--fuse_tau", "0",
     "1", "--save-segments", "--save-predictions", "--save-probs", "--explorer", "--conformal",
     "0.3"],
    ["--cost", "robotistic", "--anomalies", "--shift", "fog:2"],
]  # fmt: skip
"""Options of the evaluations of ``every_output``: together, every figure and most files."""


@pytest.fixture(scope="session")
def every_output(tiny_run, tmp_path_factory) -> list[Path]:
    """The folders of tiny evaluations with the options of ``EVERY_OUTPUT`` (of the person class,
    one example), their figures drawn in this process by ``figure_text.InProcessDrawing``, which
    keeps the figures' titles and clipped texts; the terminal's output in each ``stdout.txt``."""
    import contextlib
    import io

    from figure_text import InProcessDrawing

    from costseg.checkpoints import find_checkpoint
    from costseg.cli import evaluate_main

    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    folders = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("costseg.report.early_figures.Drawing", InProcessDrawing)
        for i, args in enumerate(EVERY_OUTPUT):
            out = tmp_path_factory.mktemp(f"every_output_{i}") / "evaluation"
            common = ["--ckpt_path", ckpt, "--output_dir", str(out), "--classes", "person"]
            with contextlib.redirect_stdout(io.StringIO()) as printed:
                evaluate_main([*common, *args, "--num_examples", "1", "--no-progress"])
            (out / "stdout.txt").write_text(printed.getvalue())
            folders.append(out)
    return folders


@pytest.fixture(autouse=True)
def recorded_figures(request, monkeypatch):
    """Figures are recorded, not drawn, unless the test is marked ``figures`` (it reads them):
    :mod:`figure_recorder`."""
    if request.node.get_closest_marker("figures") is None:
        from figure_recorder import RecordedDrawing

        from costseg.report import early_figures

        monkeypatch.setattr(early_figures, "Drawing", RecordedDrawing)
    yield
