"""The examples' outputs: their mask figures (unless drawn while the images were evaluated)
and, in TensorBoard, their masks and uncertainty maps."""

from __future__ import annotations

from dataclasses import dataclass

from torch.utils.tensorboard import SummaryWriter

from costseg.classes import CLASS_NAMES
from costseg.report.early_figures import example_figures, mask_names
from costseg.report.results import EvalResults, Examples
from costseg.report.sections import Result, Section
from costseg.report.tensorboard import log_masks
from costseg.report.uncertainty import uncertainty_strip


@dataclass
class ExampleOutputs(Examples, Result):
    """The examples; ``drawn``: their mask figures were drawn during the evaluation."""

    drawn: bool = False

    def write(self, results: EvalResults) -> Section:
        shown = mask_names([g.group for g in results.groups])
        section = Section(logs=[lambda writer: self._log(writer, shown)])
        if not self.drawn:
            section.jobs.append(
                ("evaluation", example_figures(shown, self.examples, results.subject))
            )
        return section

    def _log(self, writer: SummaryWriter, shown: list[str]) -> None:
        for i, ex in enumerate(self.examples):
            log_masks(
                writer,
                f"evaluation/masks/{i}",
                ex.image.permute(1, 2, 0).numpy(),
                ex.label.numpy(),
                {n: ex.preds[k].numpy() for k, n in enumerate(shown)},
            )
            if ex.uncertainty:
                maps = {k: v.float().numpy() for k, v in ex.uncertainty.items()}
                strip = uncertainty_strip(maps, len(CLASS_NAMES))
                writer.add_image(f"evaluation/uncertainty/{i}", strip, dataformats="HWC")
