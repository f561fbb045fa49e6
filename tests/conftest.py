"""Shared fixtures: a small Cityscapes-layout tree written into ``tmp_path``; the test session's
one tiny training and its evaluations with every output, each made once for all the xdist
workers (:func:`made_once`); figures recorded, not drawn, unless a test is marked ``figures``."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import torch
from filelock import FileLock
from PIL import Image


def pytest_configure(config: pytest.Config) -> None:
    """Under xdist, each worker's torch (and numba) threads share the CPUs with the others' (one
    thread each on two cores): more threads than cores spin against each other."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        threads = max(1, len(os.sched_getaffinity(0)) // workers)
        torch.set_num_threads(threads)
        os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))


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


def made_once(
    tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]
) -> Path:
    """The folder ``name`` shared by every process of this test session (beside the xdist
    workers' own temporary folders), filled by ``make(folder)`` once: the first worker to ask
    makes it while the others wait on a file lock, then every worker reads it. A ``make`` that
    failed leaves nothing the next one trusts."""
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / name
    made = folder.with_name(f"{name}.made")
    with FileLock(folder.with_name(f"{name}.lock")):
        if not made.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            make(folder)
            made.touch()
    return folder


class TrainerRecord(NamedTuple):
    """What the tests read of the tiny run's trainer."""

    log_dir: str
    logged_metrics: dict[str, torch.Tensor]
    callback_metrics: dict[str, torch.Tensor]


class TinyRun(NamedTuple):
    """The tiny training of :data:`TINY_TRAIN`: the trained module as it was in memory (saved
    whole, not through its checkpoint), its trainer's record and the runs folder."""

    module: torch.nn.Module
    trainer: TrainerRecord
    runs: Path


def _train_tiny(folder: Path) -> None:
    from costseg.cli import train_main

    runs = folder / "runs"
    module, trainer = train_main([*TINY_TRAIN, f"--trainer.logger.init_args.save_dir={runs}"])
    record = TrainerRecord(
        trainer.log_dir, dict(trainer.logged_metrics), dict(trainer.callback_metrics)
    )
    torch.save({"module": module, "trainer": record._asdict()}, folder / "trained.pt")


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> TinyRun:
    """A tiny model trained through `train_main` (2 steps), once per test session."""
    folder = made_once(tmp_path_factory, "tiny_run", _train_tiny)
    trained = torch.load(folder / "trained.pt", map_location="cpu", weights_only=False)
    return TinyRun(trained["module"], TrainerRecord(**trained["trainer"]), folder / "runs")


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
     "--sweep", "0.5", "--target", "person:roi0:recall>=0.05", "--maximize",
     "person:roi0:precision", "--guarantee", "0.5", "--design", "lagrangian", "--design_budget",
     "9", "--require", "person:roi0:recall>=0.05", "road:roi0:precision>=0.05",
     "--design_delta", "0.5", "--meta", "--meta_split", "train", "--meta_images", "6", "--fuse",
     "ml", "--save-segments", "--save-predictions", "--save-probs", "--explorer", "--conformal",
     "0.3", "--anomalies", "--calibration_split", "train", "--batch_size", "1",
     "--monitor_require", "person:roi0:recall>=0.5", "road:roi0:precision>=0.9",
     "--monitor_delay", "1"],
    ["--cost", "robotistic", "--anomalies", "--shift", "fog:2", "--alpha_sweep", "0.5",
     "--defer_sweep", "0.2", "0.6", "0.2", "--meta", "--meta_split", "train", "--meta_images",
     "6", "--fuse", "ml", "--fuse_tau", "0", "1"],
]  # fmt: skip
"""Options of the evaluations of ``every_output``: the first runs every analysis of the table,
together they write every file and draw every figure."""


def every_output_arguments(ckpt: Path, out: Path, case: int) -> list[str]:
    """The arguments of the evaluation ``EVERY_OUTPUT[case]`` (of the person class, two
    examples) into ``out``."""
    common = ["--ckpt_path", str(ckpt), "--output_dir", str(out), "--classes", "person"]
    return [*common, *EVERY_OUTPUT[case], "--num_examples", "2", "--no-progress"]


@pytest.fixture(scope="session")
def every_output(tiny_run: TinyRun, tmp_path_factory) -> list[Path]:
    """The folders of the evaluations of ``EVERY_OUTPUT``, made once per test session on one
    thread (as torchrun runs each process: the network's float sums are then the same), their
    figures drawn in that process by ``figure_text.InProcessDrawing``. Beside each folder: the
    terminal's output (``stdout.txt``); beside all: every figure's titles and clipped texts
    (``figures.json``)."""
    from costseg.checkpoints import find_checkpoint
    from costseg.cli import evaluate_main

    def make(folder: Path) -> None:
        from figure_text import InProcessDrawing

        ckpt = find_checkpoint(None, runs_dir=tiny_run.runs)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with pytest.MonkeyPatch.context() as patch:
                patch.setattr("costseg.report.early_figures.Drawing", InProcessDrawing)
                for case in range(len(EVERY_OUTPUT)):
                    arguments = every_output_arguments(
                        ckpt, folder / str(case) / "evaluation", case
                    )
                    with contextlib.redirect_stdout(io.StringIO()) as printed:
                        evaluate_main(arguments)
                    (folder / str(case) / "stdout.txt").write_text(printed.getvalue())
        finally:
            torch.set_num_threads(threads)
        drawn = {"titles": InProcessDrawing.titles, "clipped": InProcessDrawing.clipped}
        (folder / "figures.json").write_text(json.dumps(drawn))

    folder = made_once(tmp_path_factory, "every_output", make)
    return [folder / str(case) / "evaluation" for case in range(len(EVERY_OUTPUT))]


@pytest.fixture(scope="session")
def every_figure(every_output: list[Path]) -> dict:
    """The figures of ``every_output``: ``titles`` (tag → the figure's titles) and ``clipped``
    (``"<tag>: <text>"`` of every text cut off at the saved size)."""
    return json.loads((every_output[0].parents[1] / "figures.json").read_text())


IMPORT_STEPS = {
    "the model": "import costseg.models, costseg.networks.costseg",
    "an evaluation": "import costseg.cli, costseg.evaluation.run, costseg.report.evaluation, "
    "costseg.networks",
    "a checkpoint loaded": "from costseg.networks import load_network; load_network({network!r})",
}
"""What a fresh interpreter runs, step after step (lightest first), in :func:`imported`."""


@pytest.fixture(scope="session")
def imported(tiny_run: TinyRun, tmp_path_factory) -> dict[str, set[str]]:
    """Step of :data:`IMPORT_STEPS` → the top-level packages in ``sys.modules`` once it ran
    (after the steps before it), in one fresh interpreter per test session; the checkpoint it
    loads is the tiny run's."""
    from costseg.checkpoints import find_checkpoint

    def make(folder: Path) -> None:
        network = f"costseg:{find_checkpoint(None, runs_dir=tiny_run.runs)}"
        code = ["import json, sys", "found = {}"]
        for step, line in IMPORT_STEPS.items():
            code.append(line.format(network=network))
            code.append(f"found[{step!r}] = sorted({{m.split('.')[0] for m in sys.modules}})")
        code.append("print(json.dumps(found))")
        done = subprocess.run(
            [sys.executable, "-c", "\n".join(code)], capture_output=True, text=True, check=True
        )
        (folder / "imported.json").write_text(done.stdout)

    found = json.loads(
        (made_once(tmp_path_factory, "imported", make) / "imported.json").read_text()
    )
    return {step: set(packages) for step, packages in found.items()}


def in_this_process(num_workers: int) -> dict:
    """:func:`costseg.workers.loader_options` for a handful of tiny images: no worker process
    (each imports torch and the dataset's modules, seconds, to load a few images)."""
    return {"num_workers": 0}


@pytest.fixture(autouse=True)
def as_in_tests(request, monkeypatch):
    """Figures are recorded, not drawn, unless the test is marked ``figures`` (it reads them:
    :mod:`figure_recorder`); data loaders read their items in the test process unless the test
    is marked ``workers`` (it runs them as outside the tests)."""
    if request.node.get_closest_marker("figures") is None:
        from figure_recorder import RecordedDrawing

        from costseg.report import early_figures

        monkeypatch.setattr(early_figures, "Drawing", RecordedDrawing)
    if request.node.get_closest_marker("workers") is None:
        from costseg import workers

        monkeypatch.setattr(workers, "loader_options", in_this_process)
    yield
