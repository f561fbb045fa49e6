"""``train.py``: LightningCLI wiring, priors before the first step, resuming.

:func:`costseg.cli.train_main` calls :func:`run_training` once Lightning is needed.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

import torch
from jsonargparse import ArgumentError, Namespace
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch import LightningDataModule, Trainer
from lightning.pytorch.callbacks import RichProgressBar, TQDMProgressBar
from lightning.pytorch.cli import LightningCLI

from costseg import workers
from costseg.checkpoints import find_checkpoint, read_checkpoint
from costseg.data.priors import roi_map, save_priors
from costseg.models.adapter import ADAPTER, NetworkOutputError, network_output_error
from costseg.training.module import SegmentationModule
from costseg.training.precision import choose_precision, cpu_has_native_bf16
from costseg.training.progress import StepProgress


class TrainCLI(LightningCLI):
    """LightningCLI with ``--ckpt_path`` to resume (``last`` = the newest ``runs/**/last.ckpt``),
    the class count checked against the dataset's before anything is built, and a run of
    another network than its config's named after that network."""

    def __init__(self, *cli_args: Any, args: Sequence[str], **kwargs: Any) -> None:
        self.command_line = list(args)
        super().__init__(*cli_args, args=self.command_line, **kwargs)

    def add_arguments_to_parser(self, parser) -> None:
        parser.add_argument(
            "--ckpt_path",
            type=str | None,
            default=None,
            help="resume training from this checkpoint ('last': newest runs/**/last.ckpt)",
        )
        parser.link_arguments("model.num_classes", "model.net.init_args.num_classes")

    def before_instantiate_classes(self) -> None:
        """Check the class count, name the run, and fill in the precision when neither the
        config nor the command line sets it."""
        _check_class_count(self.config)
        _name_after_network(self.config, self.command_line)
        precision = self.config.get("trainer.precision")
        if precision is None:
            precision, why = choose_precision(self.config.get("trainer.accelerator", "auto"))
            self.config["trainer.precision"] = precision
        else:
            why = "set by the config or --trainer.precision"
        self.precision_line = f"precision: {precision} ({why})"

    def after_instantiate_classes(self) -> None:
        """The checkpoint records the config's ``model.net`` entry, which rebuilds the network."""
        net = self.config["model"]["net"]
        init_args = net.get("init_args")
        self.model.hparams["net"] = {
            "class_path": net["class_path"],
            "init_args": init_args.as_dict() if init_args else {},
        }


@contextlib.contextmanager
def _held_messages() -> Iterator[None]:
    """Hold Lightning's log lines and warnings while the run is set up; show them only if the
    set-up succeeds, so that a bad option ends with exactly one line on stderr."""
    loggers = [logging.getLogger(n) for n in ("lightning.pytorch", "lightning.fabric")]
    saved = [(lg.handlers, lg.propagate) for lg in loggers]
    records: list[logging.LogRecord] = []
    hold = logging.Handler()
    hold.emit = records.append  # type: ignore[method-assign]
    for lg in loggers:
        lg.handlers, lg.propagate = [hold], False
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.filterwarnings("ignore", "LightningCLI's args parameter")
            yield
    finally:
        for lg, (handlers, propagate) in zip(loggers, saved, strict=True):
            lg.handlers, lg.propagate = handlers, propagate
    for record in records:
        logging.getLogger(record.name).handle(record)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def run_training(args: Sequence[str]) -> tuple[SegmentationModule, Trainer]:
    """Parse and check ``args`` (a config and overrides), compute priors or resume, and fit.

    A run that fails or is interrupted before its first step leaves no run folder; an
    interrupted one says where its ``last.ckpt`` is (KeyboardInterrupt with that message)."""
    with _held_messages():
        cli = _parse(args)
        model, data, trainer = cli.model, cli.datamodule, cli.trainer
        _check(model, data, trainer, cli.config.get("trainer.precision"))
        ckpt_path = cli.config.get("ckpt_path")
        if ckpt_path:
            ckpt_path = str(find_checkpoint(ckpt_path))
            read_checkpoint(ckpt_path, data.class_names)
    print(cli.precision_line)
    _warn_slow_bf16(trainer)
    _use_step_progress(trainer)
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(_no_interrupt_note)
    model.data_config = _data_config(cli)
    new_run = _first_missing(Path(trainer.log_dir)) if trainer.log_dir else None
    try:
        if ckpt_path:
            print(f"resuming from {ckpt_path}")
        else:
            with workers.loader_errors("the labels of the priors"):
                model.priors = _compute_priors(model, data, trainer)
        with warnings.catch_warnings(), workers.loader_errors("the data"):
            # Lightning's pytree helpers call an API that torch deprecates, at every start
            warnings.filterwarnings("ignore", r"`isinstance\(treespec, LeafSpec\)`", FutureWarning)
            trainer.fit(model, data, ckpt_path=ckpt_path)
    except BaseException as err:
        _after_failure(trainer, new_run, err)
    if trainer.checkpoint_callback is not None:
        print(f"checkpoints: {trainer.checkpoint_callback.dirpath}")
    return model, trainer


def _parse(args: Sequence[str]) -> TrainCLI:
    try:
        return TrainCLI(
            SegmentationModule,
            LightningDataModule,
            subclass_mode_data=True,
            run=False,
            args=list(args),
            save_config_kwargs={"overwrite": True},
            parser_kwargs={"exit_on_error": False},
        )
    except ArgumentError as err:
        # jsonargparse takes a function returning a module as model.net, then fails on the
        # num_classes link; train.py takes such a function through the adapter.
        if "linked_targets" not in str(err):
            raise
        raise ValueError(
            f"model.net names a function, and takes only nn.Module classes: pass --model.net "
            f"{ADAPTER} --model.net.init_args.builder {_net_class_path(args) or 'FUNCTION'} "
            '(docs/usage.md, "Your own network")'
        ) from err
    except MisconfigurationException as err:
        if "gpu backend" not in str(err).lower():
            raise
        raise ValueError(
            "this config trains on a GPU (trainer.accelerator: gpu) and none is found; on the "
            "CPU add --trainer.accelerator cpu --trainer.precision 32-true (slow)"
        ) from err


def _net_class_path(args: Sequence[str]) -> str | None:
    """The ``model.net`` class path given on the command line, or None."""
    for i, arg in enumerate(args):
        for key in ("--model.net", "--model.net.class_path"):
            if arg == key and i + 1 < len(args):
                return args[i + 1]
            if arg.startswith(f"{key}="):
                return arg.split("=", 1)[1]
    return None


def _check(
    model: SegmentationModule, data: LightningDataModule, trainer: Trainer, precision: Any
) -> None:
    """Options that Lightning accepts but that cannot train: refused before any priors."""
    _check_precision(precision, trainer)
    if model.loss.uses_priors == "pixel" and hasattr(getattr(data, "settings", None), "crop_size"):
        raise ValueError(
            f"model.loss {type(model.loss).__name__} with pixel-wise priors needs training labels "
            "at the priors' size, and this data trains on random crops: use priors: global"
        )
    if trainer.max_steps < 1 and not trainer.fast_dev_run:
        raise ValueError(
            f"--trainer.max_steps must be >= 1 (the optimiser steps to train), "
            f"got {trainer.max_steps}"
        )
    _check_data(data)
    _check_network(model)


def _check_class_count(config: Any) -> None:
    """``model.num_classes`` against the class count of the data's class, before the module
    (whose validation rules name classes) or the data are built."""
    path = str(config.get("data.class_path") or "")
    module, _, name = path.rpartition(".")
    try:
        classes = getattr(importlib.import_module(module), name).num_classes
    except (ImportError, AttributeError, ValueError):
        return  # no such class, or one without a class count: LightningCLI names the first
    asked = config.get("model.num_classes")
    if isinstance(classes, int) and asked != classes:
        raise ValueError(
            f"--model.num_classes is {asked}, and the dataset ({name}) has {classes} classes: "
            f"pass --model.num_classes {classes}"
        )


PRECISION_NAMES = {"16": "16-mixed", "bf16": "bf16-mixed", "32": "32-true", "64": "64-true"}
"""Lightning's short precisions and the names it gives them."""


def _check_precision(asked: Any, trainer: Trainer) -> None:
    """The precision asked for is the one Lightning trains in, with float32 weights."""
    asked = PRECISION_NAMES.get(str(asked), str(asked))
    if asked in ("16-true", "bf16-true"):
        raise ValueError(
            f"--trainer.precision {asked} keeps the weights in 16 bits, and costseg trains "
            "float32 weights (the inputs are normalised in float32): pass bf16-mixed, 16-mixed "
            "(on a GPU) or 32-true"
        )
    if asked != str(trainer.precision):  # e.g. 16-mixed on a CPU: Lightning takes bf16-mixed
        where = type(trainer.accelerator).__name__.removesuffix("Accelerator").lower()
        raise ValueError(
            f"--trainer.precision {asked} is not available on this accelerator ({where}; "
            f"Lightning would train in {trainer.precision}): pass --trainer.precision "
            f"{trainer.precision} or 32-true"
        )


def _check_data(data: LightningDataModule) -> None:
    """The training and validation splits exist (a Cityscapes root lists its files; the
    datasets are kept for training)."""
    try:
        data.setup("fit")
    except FileNotFoundError as err:
        raise ValueError(f"--data.init_args.root: {err}") from None


def _name_after_network(config: Any, command_line: Sequence[str]) -> None:
    """A run of another network than its first config's is named after that network (its
    ``runs/<name>/``), unless the command line names the run."""
    logger = config.get("trainer.logger")
    init_args = logger.get("init_args") if isinstance(logger, Namespace) else None
    named = any(
        arg.split("=", 1)[0] in ("--trainer.logger", "--trainer.logger.name")
        or arg.startswith("--trainer.logger.init_args.name")
        for arg in command_line
    )
    configs = config.get("config") or []
    if init_args is None or init_args.get("name") is None or named or not configs:
        return
    import yaml

    with open(str(configs[0])) as f:
        base = (yaml.safe_load(f) or {}).get("model", {}).get("net")
    net = config.get("model.net")
    if net is not None and _network_name(net) != _network_name(base):
        init_args["name"] = _network_name(net)


def _network_name(entry: Any) -> str | None:
    """The name of a ``model.net`` entry's network: an adapter's builder's, else its class's."""
    if isinstance(entry, Namespace):
        entry = entry.as_dict()
    if not isinstance(entry, dict):
        return None
    path = str(entry.get("class_path", ""))
    if path == ADAPTER:
        path = str((entry.get("init_args") or {}).get("builder", path))
    return path.rpartition(".")[2]


def _check_network(model: SegmentationModule) -> None:
    """One forward pass of the network in eval mode on a small image: its output must be
    logits of ``num_classes`` classes (:mod:`costseg.models.adapter`). A network that cannot
    run at this size is left to training, which runs it at the data's size."""
    was_training = model.net.training
    try:
        with torch.no_grad():
            out = model.net.eval()(torch.zeros(1, 3, 64, 64))
    except NetworkOutputError:
        raise
    except Exception:
        return
    finally:
        model.net.train(was_training)
    error = network_output_error(model.net, out, model.hparams.num_classes, batch=1)
    if error:
        raise ValueError(error)


def _first_missing(folder: Path) -> Path | None:
    """The outermost of ``folder`` and its parents that does not exist yet (None: it exists)."""
    if folder.exists():
        return None
    while not folder.parent.exists():
        folder = folder.parent
    return folder


def _after_failure(trainer: Trainer, new_run: Path | None, err: BaseException) -> NoReturn:
    """Remove a run folder that holds no training yet; re-raise ``err`` (an interrupt, which
    Lightning turns into exit status 1, as KeyboardInterrupt saying where last.ckpt is)."""
    started = trainer.global_step > 0
    if new_run is not None and not started and trainer.is_global_zero:
        shutil.rmtree(new_run, ignore_errors=True)
    interrupted = isinstance(err, KeyboardInterrupt) or (
        isinstance(err, SystemExit) and trainer.interrupted
    )
    if not interrupted:
        if isinstance(err, OSError) and err.errno is not None and not err.filename:
            # a system error without its file, e.g. a full disk under TensorBoard
            err.filename = trainer.log_dir
        raise err
    last = _newest_last(trainer)
    if last is None:
        raise KeyboardInterrupt("no checkpoint was written") from None
    raise KeyboardInterrupt(f"resume with --ckpt_path {last}") from None


def _no_interrupt_note(record: logging.LogRecord) -> bool:
    """Drop Lightning's note on Ctrl-C: the one line printed is the CLI's."""
    return "Detected KeyboardInterrupt" not in record.getMessage()


def _newest_last(trainer: Trainer) -> Path | None:
    callback = trainer.checkpoint_callback
    dirpath = getattr(callback, "dirpath", None)
    last = Path(dirpath) / "last.ckpt" if dirpath else None
    return last if last is not None and last.is_file() else None


def _use_step_progress(trainer: Trainer) -> None:
    """Lightning's default progress bar → :class:`StepProgress` (steps; lines in a log file)."""
    for i, callback in enumerate(trainer.callbacks):
        if type(callback) in (TQDMProgressBar, RichProgressBar):
            trainer.callbacks[i] = StepProgress()


def _warn_slow_bf16(trainer: Trainer) -> None:
    """bf16 autocast on a CPU without native bf16 (no AVX512-BF16 / AMX) is emulated: many
    times slower than float32. Say so before hours are lost."""
    on_cpu = trainer.accelerator.__class__.__name__ == "CPUAccelerator"
    bf16 = on_cpu and "bf16" in str(trainer.precision)
    if bf16 and not cpu_has_native_bf16():
        print(
            f"warning: this CPU ({torch.backends.cpu.get_cpu_capability()}) has no native "
            "bf16, so bf16 autocast is emulated and slow: pass --trainer.precision 32-true",
            file=sys.stderr,
        )


def _data_config(cli: LightningCLI) -> dict[str, Any]:
    data = cli.config["data"]
    return {"class_path": data["class_path"], "init_args": dict(data.get("init_args", {}))}


def _compute_priors(model: SegmentationModule, data, trainer: Trainer) -> torch.Tensor:
    """Pixel-wise priors from the training labels, saved (with figures) in the run folder.

    They are counted once per dataset (its labels, :meth:`prior_key`, and the smoothing) and
    kept in ``priors_cache/`` beside the runs folder (the logger's ``save_dir``, e.g.
    ``runs/``), which every run under any ``save_dir`` there shares; delete a file there to
    count its labels again."""
    from costseg.data.priors_cache import settings_key, training_priors
    from costseg.report.files import save_figure
    from costseg.report.priors import plot_priors, plot_roi_map

    settings = data.prior_key()
    save_dir = getattr(trainer.logger, "save_dir", None)
    with tempfile.TemporaryDirectory() as scratch:  # no logger folder (fast_dev_run): no cache
        cache = priors_cache(save_dir) if save_dir else Path(scratch)
        found = training_priors(
            data.prior_labels,
            cache / f"{settings_key(settings)}.pt",
            settings,
            num_classes=data.num_classes,
            sigma=model.hparams.prior_sigma,
            class_names=data.class_names,
        )
    model.priors_info = found.record | {"size": list(found.priors.shape[1:])}
    if trainer.is_global_zero and trainer.log_dir:
        run = Path(trainer.log_dir)
        save_priors(run / "priors.pt", found.priors, data.class_names)
        save_figure(plot_priors(found.priors, data.class_names), run / "priors.png")
        save_figure(plot_roi_map(roi_map(found.priors, data.class_names)), run / "roi_map.png")
    return found.priors


def priors_cache(save_dir: str | Path) -> Path:
    """The folder of the training priors' cache: ``priors_cache/`` beside the runs folder
    ``save_dir``, shared by the runs of every ``save_dir`` there.

    >>> priors_cache("/work/runs")
    PosixPath('/work/priors_cache')
    """
    return Path(save_dir).resolve().parent / "priors_cache"
