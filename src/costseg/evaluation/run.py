"""The ``evaluate.py`` job: plan (once) → the loop (:mod:`costseg.evaluation.loop`) → every
analysis's outputs (:mod:`costseg.report.evaluation`).

:func:`evaluate` plans, runs and writes; the output folder is marked ``INCOMPLETE`` until every
file is written, and a failure says where the partial outputs are. Under ``torchrun`` the
metrics' sums of all processes are merged.
"""

from __future__ import annotations

import threading

import torch.distributed as dist
from torch.utils.data import Dataset

from costseg import workers
from costseg.evaluation.analyses import figure_modules, import_analyses, wanted
from costseg.evaluation.held_out import HeldOut, held_out_images
from costseg.evaluation.loop import run
from costseg.evaluation.plan import EvalPlan, plan
from costseg.evaluation.processes import rank
from costseg.networks.sources import Source
from costseg.options import EvalOptions
from costseg.report.outputs import INCOMPLETE, mark_complete
from costseg.report.results import EvalResults
from costseg.rules import RuleGroup


def evaluate(
    opts: EvalOptions,
    source: Source | None = None,
    dataset: Dataset | None = None,
    groups: list[RuleGroup] | None = None,
) -> EvalResults | list[EvalResults]:
    """Plan, run, and (on rank 0) write every output; returns the results (a list of them, one
    per shift, with several ``--shift``: :mod:`costseg.evaluation.shifts`). ``source`` and
    ``dataset`` replace the ones the options name (:func:`costseg.api.evaluate`); ``groups``:
    the rule groups of ``opts`` already checked (:func:`~costseg.evaluation.plan.checked_groups`,
    which runs here otherwise).

    Figures known before the loop ends are drawn meanwhile, by workers of the forkserver
    (:mod:`costseg.workers`), which starts first, while the network loads. The output
    folder is marked ``INCOMPLETE`` until every file is written; an interrupt or a failed write
    says where the partial outputs are."""
    entries = [entry for entry, _ in wanted(opts)]
    workers.start(figure_modules(entries))
    prepare = threading.Thread(target=import_analyses, args=(entries,), daemon=True)
    prepare.start()  # their imports (torchmetrics, the reports) overlap the network's loading
    planned = plan(opts, source, dataset, groups)
    held_out = held_out_images(planned)
    try:
        if len(planned.shifts) > 1:
            from costseg.evaluation.shifts import evaluate_shifts

            return evaluate_shifts(planned, held_out, evaluate_plan)
        return evaluate_plan(planned, held_out)
    finally:
        for held in held_out:
            if held is not None:
                held.close()  # the held-out scores kept on disk, if any


def evaluate_plan(
    planned: EvalPlan, held_out: tuple[HeldOut | None, HeldOut | None]
) -> EvalResults:
    """Run ``planned`` on its reported images (fitting on ``held_out``, the calibration and meta
    images) and write its outputs into its output folder (see :func:`evaluate`)."""
    early, out = None, planned.output_dir
    try:
        if rank() == 0:
            from costseg.report.early_figures import EarlyFigures
            from costseg.report.results import figure_subject

            roi = planned.priors.roi_map()
            subject = figure_subject(planned.description, [str(s) for s in planned.shifts])
            early = EarlyFigures(out, planned.groups, roi, planned.num_examples, subject)
        results = run(planned, held_out, early)
        if early:
            from costseg.report.evaluation import write_evaluation

            write_evaluation(results, early)
    except (KeyboardInterrupt, ValueError, OSError, workers.Stalled, dist.DistError) as err:
        if early:
            early.cancel()
        partial = f"the partial outputs in {out} are marked {INCOMPLETE}"
        if isinstance(err, KeyboardInterrupt):
            raise KeyboardInterrupt(partial) from None
        if isinstance(err, dist.DistError):  # a peer process that stopped answering
            first = str(err).strip().splitlines()[0]
            raise workers.Stalled(f"another evaluation process: {first}; {partial}") from err
        if isinstance(err, workers.Stalled):
            raise workers.Stalled(f"{err}; {partial}") from err
        if isinstance(err, ValueError):  # bad data met on the way (an unreadable file)
            raise ValueError(f"{str(err).strip()}; {partial}") from err
        # a full disk under TensorBoard's writer thread names no file: the folder it writes in
        raise OSError(f"{err.strerror or err}: {err.filename or out}; {partial}") from err
    except BaseException:
        if early:
            early.cancel()
        raise
    if rank() == 0:
        mark_complete(out)
    return results
