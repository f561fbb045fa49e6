"""Several ``--shift`` at once: one evaluation of the reported images per shift, with the network,
the priors and the (clean) held-out images of one plan, each into
``<output_dir>/<name>_<severity>/`` as a complete evaluation folder, then the summary over the
shifts (:mod:`costseg.report.shifts`) in ``<output_dir>``."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from costseg.data.shift import Shift, ShiftedDataset
from costseg.evaluation.plan import EvalPlan, on_rank0, rank
from costseg.report.outputs import claim_output_dir, mark_complete
from costseg.report.results import EvalResults


def shift_folder(shift: Shift) -> str:
    """``fog_3`` for fog:3."""
    return f"{shift.name}_{shift.severity}"


def evaluate_shifts(
    planned: EvalPlan, evaluate_plan: Callable[[EvalPlan], EvalResults]
) -> list[EvalResults]:
    """``evaluate_plan`` once per shift of ``planned``; the summary written on rank 0."""
    from costseg.report.shifts import write_shift_summary

    out, results = planned.output_dir, []
    for shift in planned.shifts:
        folder = out / shift_folder(shift)
        print(f"shift {shift}: {folder}")
        one = dataclasses.replace(
            planned,
            options=dataclasses.replace(planned.options, shift=[str(shift)]),
            dataset=ShiftedDataset(planned.dataset, shift, planned.options.seed),
            output_dir=on_rank0(lambda folder=folder: claim_output_dir(str(folder), False, out)),
            groups=list(planned.groups),  # a fitted temperature adds a group to the run's list
            shifts=[shift],
        )
        results.append(evaluate_plan(one))
    if rank() == 0:
        folders = {str(s): shift_folder(s) for s in planned.shifts}
        write_shift_summary(out, folders, planned.class_ids)
        mark_complete(out)
    return results
