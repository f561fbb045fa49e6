"""The output folder of an evaluation, and the per-image files written during the loop.

Nothing is lost: without ``--output_dir`` each evaluation gets a new
``<base>/version_<n>``; an explicit folder that already holds files is refused unless the user
says ``--overwrite``. A claimed folder holds the marker file ``INCOMPLETE`` until
:func:`mark_complete` removes it, so an interrupted or failed run never looks finished.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from costseg.classes import label_ids
from costseg.report.files import write_png, write_text

INCOMPLETE = "INCOMPLETE"
_MARKER_TEXT = (
    "This run did not finish (interrupted or failed): the files beside this one are partial.\n"
    "Run it again, with --overwrite to reuse this folder.\n"
)


def claim_output_dir(output_dir: str | None, overwrite: bool, default_base: Path) -> Path:
    """Create and return the folder this evaluation writes into.

    Args:
        output_dir: the user's ``--output_dir``, or None for ``default_base/version_<n>``.
        overwrite: allow an ``output_dir`` that already holds files.
        default_base: where the numbered versions go.

    Raises:
        ValueError: the folder is a file, holds results (without ``overwrite``) or is not
            writable.

    >>> with tempfile.TemporaryDirectory() as d:
    ...     [claim_output_dir(None, False, Path(d)).name for _ in range(2)]
    ['version_0', 'version_1']
    """
    out = _next_version(default_base) if output_dir is None else check_free(output_dir, overwrite)
    _make_writable(out)
    write_text(out / INCOMPLETE, _MARKER_TEXT)
    return out


def mark_complete(folder: Path) -> None:
    """Remove the ``INCOMPLETE`` marker: every output of the run in ``folder`` is written."""
    (folder / INCOMPLETE).unlink(missing_ok=True)


def check_free(output_dir: str | Path, overwrite: bool) -> Path:
    """``output_dir`` as a Path; ValueError when it is a file, or holds results (or an unfinished
    run) and ``overwrite`` is not set. Nothing is created (the checks run it before anything
    heavy; :func:`claim_output_dir` claims the folder)."""
    out = Path(output_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--output_dir {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        held = "an unfinished run" if (out / INCOMPLETE).exists() else "results"
        raise ValueError(
            f"--output_dir {out} already holds {held}: pass --overwrite to replace them, "
            "or choose another folder"
        )
    return out


def _next_version(base: Path) -> Path:
    _make_writable(base)
    n = 1 + max(
        (int(p.name[8:]) for p in base.glob("version_*") if p.name[8:].isdigit()), default=-1
    )
    while True:
        try:
            (base / f"version_{n}").mkdir()  # fails if another run took it meanwhile
            return base / f"version_{n}"
        except FileExistsError:
            n += 1


def _make_writable(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as err:
        raise ValueError(f"cannot write into {folder}: {err.strerror or err}") from None


class ImageFiles:
    """The per-image files evaluate.py and predict.py write alike: each rule's Cityscapes label
    ids (``<labels>/<rule>/<stem>.png``, 255 where the rule deferred, docs/definitions.md §14) and
    the probabilities (``probs/<stem>.npz``, float16, §8, with the uncertainty maps beside them,
    §13).

    Args:
        output_dir: the job's folder.
        rule_names: the K rules, in the order of their label maps.
        labels: the folder of the label-id PNGs (``predictions``: evaluate.py, ``labels``:
            predict.py).

    >>> import numpy as np
    >>> with tempfile.TemporaryDirectory() as d:
    ...     ImageFiles(Path(d), ["a"], "labels").label_maps("x", np.zeros((1, 2, 2), np.uint8))
    ...     [p.relative_to(d).as_posix() for p in Path(d).rglob("*.png")]
    ['labels/a/x.png']
    """

    def __init__(self, output_dir: Path, rule_names: Sequence[str], labels: str) -> None:
        self.output_dir, self.rule_names, self.labels = output_dir, list(rule_names), labels

    def label_maps(self, stem: str, maps: np.ndarray) -> None:
        """(K, H, W) train-id maps of the rules (255: deferred) → one label-id PNG per rule."""
        for name, labels in zip(self.rule_names, maps, strict=True):
            write_png(self.output_dir / self.labels / name / f"{stem}.png", label_ids(labels))

    def probabilities(
        self, stem: str, probs: torch.Tensor, uncertainty: Mapping[str, torch.Tensor] | None
    ) -> None:
        """(N, H, W) probabilities and the (H, W) uncertainty maps → ``probs/<stem>.npz``."""
        from costseg.networks.probs_files import save_probs

        save_probs(self.output_dir / "probs" / f"{stem}.npz", probs, maps=uncertainty)


class BatchWriter(ImageFiles):
    """:class:`ImageFiles` of evaluate.py, a batch at a time.

    Args:
        output_dir: the evaluation folder.
        rule_names: names of the named rules, in the order of their label maps.
        predictions: write ``predictions/<rule>/<image>.png``.
    """

    def __init__(self, output_dir: Path, rule_names: list[str], predictions: bool) -> None:
        super().__init__(output_dir, rule_names, "predictions")
        self.predictions = predictions

    def save_predictions(self, stems: list[str], preds: torch.Tensor) -> None:
        """(B, K, H, W) train-id maps of the named rules (255: deferred) → one PNG per image
        and rule."""
        if not self.predictions:
            return
        for stem, maps in zip(stems, preds.cpu().numpy(), strict=True):
            self.label_maps(stem, maps)

    def save_probs(
        self, stems: list[str], probs: torch.Tensor, uncertainty: dict | None = None
    ) -> None:
        """(B, N, H, W) probabilities → ``probs/<image>.npz``, with the (B, H, W) uncertainty
        maps beside them."""
        for i, (stem, p) in enumerate(zip(stems, probs, strict=True)):
            self.probabilities(stem, p, {k: v[i] for k, v in (uncertainty or {}).items()})
