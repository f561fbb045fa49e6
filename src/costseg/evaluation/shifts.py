"""Several ``--shift`` at once: one evaluation of the reported images per shift, with the network,
the priors and the (clean) held-out images of one plan, each into
``<output_dir>/<name>_<severity>/`` as a complete evaluation folder, the clean images' in
``<output_dir>/clean/``, then the summary over the shifts (:mod:`costseg.report.shifts`) in
``<output_dir>``."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from costseg.data.shift import Shift, ShiftedDataset
from costseg.evaluation.held_out import HeldOut
from costseg.evaluation.plan import EvalPlan
from costseg.evaluation.processes import on_rank0, rank
from costseg.report.outputs import claim_output_dir, mark_complete
from costseg.report.results import EvalResults


def shift_folder(shift: Shift) -> str:
    """``fog_3`` for fog:3."""
    return f"{shift.name}_{shift.severity}"


def evaluate_shifts(
    planned: EvalPlan,
    held_out: tuple[HeldOut | None, HeldOut | None],
    evaluate_plan: Callable[[EvalPlan, tuple], EvalResults],
) -> list[EvalResults]:
    """``evaluate_plan`` once on the clean images (``<output_dir>/clean/``, unless a shift of
    severity 0, which leaves the images as they are, is among the shifts) and once per shift of
    ``planned``; the summary written on rank 0."""
    from costseg.report.shifts import CLEAN, write_shift_summary

    out, results, folders = planned.output_dir, [], {}
    clean = [] if any(s.severity == 0 for s in planned.shifts) else [None]
    for shift in [*clean, *planned.shifts]:
        name, folder = (CLEAN, CLEAN) if shift is None else (str(shift), shift_folder(shift))
        print(f"{'clean images' if shift is None else f'shift {shift}'}: {out / folder}")
        shifted = [] if shift is None else [shift]
        one = dataclasses.replace(
            planned,
            record=planned.record | {"shift": [str(s) for s in shifted]},
            dataset=_seen_through(planned, shift),
            output_dir=on_rank0(lambda f=out / folder: claim_output_dir(str(f), False, out)),
            shifts=shifted,
        )
        results.append(evaluate_plan(one, held_out))
        folders[name] = folder
    if rank() == 0:
        write_shift_summary(out, folders, planned.class_ids)
        mark_complete(out)
    return results


def _seen_through(planned: EvalPlan, shift: Shift | None):
    """The reported images seen through ``shift`` (None: as they are)."""
    if shift is None:
        return planned.dataset
    return ShiftedDataset(planned.dataset, shift, planned.seed, planned.shift_onset)
