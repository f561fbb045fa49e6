"""Export a network and its cost-based decision as one ONNX graph (docs/deploy.md).

    python scripts/export.py --ckpt_path runs/toy/version_0/checkpoints/last.ckpt \\
        --output model.onnx [--probabilities] [--overwrite]

The graph takes uint8 RGB images, the cost matrix (N x N, or N + 1 rows with a defer row),
priors and the temperature, and gives uint8 labels (255 = deferred) and the margin
(docs/definitions.md §19); ``model.json`` beside it describes them, and ``model.priors.pt``
holds a costseg checkpoint's pixel-wise priors (the format ``evaluate.py --priors`` reads).
``--network SPEC`` exports another source (``vainf:PATH``, ``hf:DIR``). The options are the
fields of :class:`costseg.options.ExportOptions`. Needs the ``onnx`` extra
(``pip install 'costseg[onnx]'``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from costseg.cli import build_parser, user_errors
from costseg.options import ExportOptions


def parser() -> argparse.ArgumentParser:
    """The command's options: the fields of :class:`ExportOptions`."""
    return build_parser(ExportOptions, "export.py", __doc__.splitlines()[0])


def main(args: Sequence[str] | None = None) -> None:
    """Parse, check (before anything loads), export; one line and exit 2 on a mistake."""
    with user_errors():
        opts = ExportOptions(**vars(parser().parse_args(args)))
        from costseg.export.job import CHECK_SIZE, export, plan_export

        done = export(plan_export(opts))
        print(f"wrote {done.graph} and {done.sidecar}")
        if done.priors_file is not None:
            print(
                f"wrote {done.priors_file}: the checkpoint's priors (evaluate.py --priors reads it)"
            )
        check = done.parity
        print(
            f"parity at {CHECK_SIZE[0]} x {CHECK_SIZE[1]} against PyTorch (docs/definitions.md "
            f"§19): {check.differing:,} of {check.pixels:,} labels differ, "
            f"{check.outside} beyond the float32 bound"
        )


if __name__ == "__main__":
    main()
