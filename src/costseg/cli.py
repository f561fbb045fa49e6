"""Command lines: ``python train.py`` and ``python evaluate.py``; only this module parses
arguments.

A user mistake ends with one line on stderr and exit status 2, Ctrl-C with one line and exit
status 130 (set ``COSTSEG_DEBUG=1`` for the traceback). The options of ``evaluate.py`` are the
fields of :class:`costseg.options.EvalOptions`; :func:`build_parser` derives the parser. Heavy
libraries (torch, Lightning) are imported only once they are needed, so ``--help`` answers at
once.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import sys
import threading
import traceback
import types
import typing
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from costseg import CONFIGS, workers
from costseg.options import EvalOptions, PredictOptions, field_default
from costseg.workers import Stalled

T = TypeVar("T")


def fail(message: str, join: bool = False) -> NoReturn:
    """Print one line ``error: message`` on stderr and exit with status 2.

    Of a multi-line message the last line is kept (an error raised in a DataLoader worker
    carries the worker's traceback before it), or, with ``join``, all lines joined; the line
    never starts with an exception's class name (:func:`error_line`).
    """
    print(f"error: {error_line(message, join)}", file=sys.stderr)
    sys.exit(2)


CLASS_PREFIX = re.compile(r"(?:[A-Za-z_]\w*\.)*[A-Z]\w*(?:Error|Exception|Stalled|Exit):\s*")
"""``ValueError: ``, ``torch.OutOfMemoryError: ``: how a traceback's last line starts."""


def error_line(message: str, join: bool = False) -> str:
    """The one line of an error message: its last line (with ``join``: all lines joined),
    without the exception class names a traceback puts before it.

    >>> error_line("Traceback ...\\nValueError: image a.png is (4, 8), its label (8, 16)")
    'image a.png is (4, 8), its label (8, 16)'
    """
    lines = [line.strip() for line in str(message).strip().splitlines()] or ["unknown error"]
    line = " ".join(lines) if join else lines[-1]
    while (prefix := CLASS_PREFIX.match(line)) and line[prefix.end() :]:
        line = line[prefix.end() :]
    return line


def interrupted(message: str = "") -> NoReturn:
    """Print one line ``interrupted[: message]`` on stderr and exit with status 130 (Ctrl-C)."""
    print(f"interrupted{': ' + message if message else ''}", file=sys.stderr)
    sys.exit(130)


@contextlib.contextmanager
def user_errors(*extra: type[BaseException]) -> Iterator[None]:
    """Turn a user mistake (ValueError, OSError and ``extra``) or a stalled worker
    (:class:`costseg.workers.Stalled`) into one line and exit status 2,
    and Ctrl-C into one line (the interrupt's message: where partial outputs are) and 130.

    An OSError in another thread (a full disk under TensorBoard's writer thread) prints no
    traceback there: it ends the job here, in one line, unless the main thread has already
    raised it (TensorBoard's writer does at its next call).
    """
    in_threads: list[OSError] = []
    default_hook = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        if isinstance(args.exc_value, OSError) and not os.environ.get("COSTSEG_DEBUG"):
            in_threads.append(args.exc_value)
        else:
            default_hook(args)

    threading.excepthook = hook
    try:
        yield
        if in_threads:
            raise in_threads[0]
    except KeyboardInterrupt as err:
        if os.environ.get("COSTSEG_DEBUG"):
            raise
        interrupted(str(err))
    except (ValueError, OSError, Stalled, *extra) as err:
        if os.environ.get("COSTSEG_DEBUG"):
            raise
        err = own_cause(err)
        message = str(err) or f"failed without a message ({err.__class__.__name__})"
        fail(message, isinstance(err, argparse.ArgumentError))
    finally:
        threading.excepthook = default_hook


def own_cause(err: BaseException) -> BaseException:
    """The ValueError that costseg's own code raised behind ``err`` (LightningCLI's parser
    wraps an error of a class it instantiates, e.g. a loss's bad setting, in a list of the
    types it tried), else ``err``."""
    cause = err.__cause__
    while isinstance(cause, ValueError):
        frames = traceback.extract_tb(cause.__traceback__)
        if frames and Path(frames[-1].filename).is_relative_to(Path(__file__).parent):
            return cause
        cause = cause.__cause__
    return err


def train_main(args: Sequence[str] | None = None) -> tuple[Any, Any]:
    """``python train.py [--config toy] [--trainer.max_steps 100] ...``.

    Returns:
        the trained module and its trainer (for scripts and tests).
    """
    args = list(sys.argv[1:] if args is None else args)
    if not any(a == "--config" or a.startswith("--config=") for a in args):
        args = ["--config", "toy", *args]
    for i, arg in enumerate(args):
        if arg.startswith("--config="):
            args[i] = f"--config={config_path(arg.split('=', 1)[1])}"
        elif i and args[i - 1] == "--config":
            args[i] = config_path(arg)
    if "-h" in args or "--help" in args:
        print_train_help(args)
        sys.exit(0)
    if "--help_all" in args:  # LightningCLI's own help: every option of every class (slow)
        args[args.index("--help_all")] = "--help"
    with user_errors():
        from jsonargparse import ArgumentError
        from lightning.fabric.utilities.exceptions import MisconfigurationException

        from costseg.training.run import run_training

        with user_errors(ArgumentError, MisconfigurationException):
            try:
                return run_training(args)
            except ModuleNotFoundError as err:
                # Lightning's "Requirement 'torch_xla>=1.13' not met. HINT: pip install ...": a
                # package the chosen option needs (--trainer.accelerator tpu) is the user's to
                # install; any other failed import is a bug, with its traceback.
                if str(err).startswith("Requirement '"):
                    raise ValueError(str(err)) from None
                raise


def config_path(value: str) -> str:
    """A ``--config`` value as a file: an existing file as given, else a packaged config by name
    (``toy``, ``cityscapes.yaml``, ``configs/toy.yaml``, ``losses/focal``); anything else is
    left as it is.

    >>> Path(config_path("toy")).name, Path(config_path("losses/focal")).parent.name
    ('toy.yaml', 'losses')
    >>> config_path("configs/none.yaml")
    'configs/none.yaml'
    """
    path = Path(value)
    if path.is_file() or path.is_absolute() or ".." in path.parts:
        return value
    parts = path.parts[1:] if path.parts[:1] == ("configs",) else path.parts
    if not parts:
        return value
    name = parts[-1] if path.suffix in (".yaml", ".yml") else f"{parts[-1]}.yaml"
    packaged = CONFIGS.joinpath(*parts[:-1], name)
    return str(packaged) if packaged.is_file() else value


def print_train_help(args: Sequence[str]) -> None:
    """A fast ``train.py --help``: usage and every key of the chosen config with its value.

    LightningCLI's own help needs Lightning imported (~10 s on 2 cores): ``--help_all``.
    """
    import yaml

    path = Path(
        args[args.index("--config") + 1]
        if "--config" in args
        else next(a.split("=", 1)[1] for a in args if a.startswith("--config="))
    )
    print(
        "usage: train.py [--config FILE|toy|toy_long|cityscapes] [--KEY VALUE ...] "
        "[--ckpt_path PATH|last] [--print_config] [--help_all]\n\n"
        "Train DeepLabv3+ with LightningCLI. Every key of the config can be overridden, e.g.\n"
        "  python train.py --trainer.max_steps 3000 --model.net.init_args.backbone resnet34\n"
        "  python train.py --config cityscapes --data.init_args.root DIR\n"
        "  python train.py --config toy --config losses/focal   # a loss of configs/losses/\n"
        "  python train.py --ckpt_path last        # resume the newest runs/**/last.ckpt\n"
        "Another network (torchvision's builders, a dict output): docs/usage.md, "
        '"Your own network".\n'
        "--help_all lists every option of the trainer, model and data classes.\n\n"
        f"Keys of {path} and their values:"
    )
    try:
        config = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        fail(f"cannot read --config {path}: {err}")
    for key, value in _flatten(config):
        print(f"  --{key} {value}")


def _flatten(config: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(config, dict):
        for key, value in config.items():
            yield from _flatten(value, f"{prefix}{key}.")
    else:
        yield prefix.rstrip("."), config


class OneLineParser(argparse.ArgumentParser):
    """argparse, with every parsing error as one line on stderr (exit status 2)."""

    def error(self, message: str) -> NoReturn:
        fail(f"{self.prog}: {message}")


def build_parser(options: type, prog: str | None, description: str) -> argparse.ArgumentParser:
    """The parser of an options dataclass (:mod:`costseg.options`, or a script's own): one
    argument per field.

    A field's type says the rest: ``bool`` is a flag (``--no-x`` when it defaults to True),
    ``list[...]`` takes several values, ``Literal[...]`` lists the choices; a field with
    ``init=False`` is no option, one whose ``flag`` has no dashes a positional argument. A
    script that shares some of a job's options declares them with
    :func:`costseg.options.same_option`.

    >>> from costseg.options import EvalOptions, PredictOptions
    >>> p = build_parser(EvalOptions, "evaluate.py", "")
    >>> p.parse_args(["--limit", "2", "--no-progress"]).limit
    2
    """
    parser = OneLineParser(prog=prog, description=description)
    groups: dict[str | None, Any] = {None: parser}
    hints = typing.get_type_hints(options)
    for f in dataclasses.fields(options):
        if not f.init:  # a value derived from the options, not one
            continue
        meta = dict(f.metadata)
        title = meta.pop("group", None)
        meta.pop("candidates", None)
        meta.pop("needs", None)
        if title not in groups:
            groups[title] = parser.add_argument_group(title)
        flag = meta.pop("flag", f"--{f.name}")
        names = {"dest": f.name} if flag.startswith("-") else {}
        if not names:  # a positional argument, shown as its flag
            flag, meta["metavar"] = f.name, meta.get("metavar", flag)
        argument = _argument(field_default(f), hints[f.name], meta)
        groups[title].add_argument(flag, **names, **argument)
    return parser


def parse_options(
    options: type[T], args: Sequence[str] | None = None, prog: str | None = None, about: str = ""
) -> T:
    """The dataclass ``options`` filled from the command line ``args`` (default: the process's)
    by :func:`build_parser`: a mistake ends in one line on stderr and exit status 2.

    >>> from costseg.options import ExportOptions
    >>> parse_options(ExportOptions, ["--output", "m.onnx", "--probabilities"]).probabilities
    True
    """
    return options(**vars(build_parser(options, prog, about).parse_args(args)))


def _argument(default: Any, hint: Any, meta: dict[str, Any]) -> dict[str, Any]:
    """argparse keywords of one dataclass field (its type ``hint``, ``meta`` data)."""
    optional = typing.get_origin(hint) in (typing.Union, types.UnionType)
    kind = [a for a in typing.get_args(hint) if a is not type(None)] if optional else [hint]
    if hint is bool:
        return {"action": "store_false" if default else "store_true", "help": meta["help"]}
    meta["default"] = default
    if default is not None:
        shown = " ".join(map(str, default)) if isinstance(default, list) else default
        meta["help"] = f"{meta['help']} (default: {shown})"
    if typing.get_origin(kind[0]) is list:
        meta.setdefault("nargs", "+")
        kind = list(typing.get_args(kind[0]))
    if typing.get_origin(kind[0]) is typing.Literal:
        meta["choices"] = typing.get_args(kind[0])
        if all(isinstance(c, int) for c in meta["choices"]):
            meta.setdefault("type", int)
    elif kind[0] in (int, float):
        meta.setdefault("type", kind[0])
    return meta


def evaluate_parser() -> argparse.ArgumentParser:
    """The options of ``evaluate.py``: the fields of :class:`EvalOptions`."""
    return build_parser(
        EvalOptions,
        "evaluate.py",
        "Evaluate a network under cost-based decision rules: per-class precision "
        "and recall in regions of interest, FP/FN segments, mIoU; tables, figures, JSON, "
        "TensorBoard; optionally sweeps over the value-space triangle and the α path.",
    )


def evaluate_main(args: Sequence[str] | None = None) -> Any:
    """``python evaluate.py --cost egoistic`` (see ``--help``); returns the results."""
    with user_errors():
        opts = EvalOptions(**vars(evaluate_parser().parse_args(args)))
        from costseg.evaluation.analyses import figure_modules, wanted
        from costseg.evaluation.plan import checked_groups

        groups = checked_groups(opts)  # before the forkserver, a network or data is touched
        # the workers' forkserver imports the figures' modules while this process goes on
        workers.start(figure_modules([entry for entry, _ in wanted(opts)]))
        from costseg.evaluation.run import evaluate

        return evaluate(opts, groups=groups)


def predict_parser() -> argparse.ArgumentParser:
    """The options of ``predict.py``: the fields of :class:`PredictOptions`."""
    return build_parser(
        PredictOptions,
        "predict.py",
        "Apply cost-based decision rules to your own images or videos (no labels): panels, "
        "label and colour PNGs, counts; optionally the explorer page.",
    )


def predict_main(args: Sequence[str] | None = None) -> Path:
    """``python predict.py --input photo.jpg`` (see ``--help``); returns the output folder."""
    with user_errors():
        opts = PredictOptions(**vars(predict_parser().parse_args(args)))
        from costseg.prediction import predict

        return predict(opts)


# The console scripts (`costseg-train`, ...): a console script exits with its function's return
# value, so these return None (exit status 0) where the *_main functions return their results.
def train_script() -> None:
    train_main()


def evaluate_script() -> None:
    evaluate_main()


def predict_script() -> None:
    predict_main()
