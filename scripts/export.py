"""Export a network and its cost-based decision as one ONNX graph (docs/deploy.md).

    python scripts/export.py --ckpt_path runs/toy/version_0/checkpoints/last.ckpt \\
        --output model.onnx [--probabilities] [--overwrite]

The graph takes uint8 RGB images, the cost matrix (N x N, or N + 1 rows with a defer row),
priors and the temperature, and gives uint8 labels (255 = deferred) and the margin
(docs/definitions.md §19); ``model.json`` beside it describes them, and ``model.priors.npy``
holds a costseg checkpoint's pixel-wise priors. ``--network SPEC`` exports another source
(``vainf:PATH``, ``hf:DIR``). Needs the ``onnx`` extra (``pip install 'costseg[onnx]'``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from costseg.cli import user_errors


def parser() -> argparse.ArgumentParser:
    """The command's options."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--ckpt_path", nargs="+", help="a train.py checkpoint (default: the newest)")
    p.add_argument("--network", nargs="+", metavar="SPEC", help="another source: vainf:PATH, ...")
    p.add_argument("--mc_dropout", type=int, metavar="N", help="refused: no single graph")
    p.add_argument("--output", required=True, help="the graph to write (.onnx)")
    p.add_argument("--probabilities", action="store_true", help="also output the probabilities")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier export")
    return p


def main(args: Sequence[str] | None = None) -> None:
    """Parse, check (before anything loads), export; one line and exit 2 on a mistake."""
    opts = parser().parse_args(args)
    with user_errors():
        from costseg.export.job import export, plan_export

        plan = plan_export(
            opts.ckpt_path, opts.network, opts.mc_dropout, opts.output, opts.probabilities,
            opts.overwrite,
        )  # fmt: skip
        path = export(plan)
        print(f"wrote {path} and {plan.sidecar}")


if __name__ == "__main__":
    main()
