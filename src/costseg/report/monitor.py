"""The outputs of ``--monitor_require`` (docs/definitions.md §22): per frame θ_t, each loss of the
monitored and of the fixed (start) matrix, their running averages and the long-run bound in
``monitor.csv``; the long-run risks beside α and the bound, windows in violation and the
agreement with argmax in results.json and table.md; two figures (the running risks against α
with the shift's onset marked, θ over the frames)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from costseg.calibration.monitor import StreamTrace, running_mean, window_violations
from costseg.report.drawing import job
from costseg.report.files import write_csv
from costseg.report.monitor_figures import monitor_figures
from costseg.report.results import EvalResults, figure_subject
from costseg.report.sections import Result, Section
from costseg.report.tables import format_value, markdown_table

WINDOW = 50
"""Frames per window of the share of windows in violation."""


@dataclass(frozen=True)
class FrameCounts:
    """One frame under one matrix: (K,) losses (NaN: undefined), labelled pixels decided as
    argmax, labelled pixels."""

    losses: np.ndarray
    agree: int
    labelled: int


@dataclass
class StreamOutcome(Result):
    """A stream walked by the monitor (T frames, K constraints).

    Attributes:
        texts, alphas: the requirements and their levels; ``eta``, ``scale``, ``delay``,
            ``share`` (of frames labelled), ``start`` (a cost file or None: μ = 0), ``base``
            (C₀), ``mu_max``, ``space`` (``whole`` or ``regional``): the monitor's settings.
        stems: the frames' names, in order; ``trace``: θ and the losses frame by frame;
            ``mu``: (T + 1, K) the multipliers of ``trace.theta``.
        fixed, monitored: per frame, the fixed (start) matrix's counts and the monitor's.
        onset: the position of the first shifted frame (None: no shift).
        record_bytes, kept_pixels: (T,) each frame's record.
    """

    texts: Sequence[str]
    alphas: Sequence[float]
    eta: float
    scale: str
    delay: int
    share: float
    start: str | None
    base: str
    mu_max: float
    space: str
    stems: list[str]
    trace: StreamTrace
    mu: np.ndarray
    fixed: list[FrameCounts]
    monitored: list[FrameCounts]
    onset: int | None
    record_bytes: np.ndarray
    kept_pixels: np.ndarray

    @property
    def fixed_losses(self) -> np.ndarray:
        return np.array([f.losses for f in self.fixed]).reshape(len(self.fixed), len(self.texts))

    def guarantee(self) -> str:
        """What the bound says, in words."""
        return (
            "For any sequence of frames, each requirement's mean loss over the labelled frames "
            "with a defined loss is at most α + (θ_end − θ_start + what the cap cut off) / (η n) "
            "(n those frames; while labels are on their way, each counts as a loss of 1). It is "
            "a long-run average over this stream, not the probability over a draw of images "
            "that a certified design gives (docs/definitions.md §20)."
        )

    def record(self) -> dict:
        """The results.json record."""
        trace, fixed = self.trace, self.fixed_losses
        window = min(WINDOW, len(self.stems)) or 1
        after = slice(self.onset, None) if self.onset is not None else None
        requirements = {}
        for i, (text, alpha) in enumerate(zip(self.texts, self.alphas, strict=True)):
            mine, theirs = trace.losses[:, i], fixed[:, i]
            requirements[text] = {
                "alpha": alpha,
                "fixed_risk": _mean(theirs),
                "monitored_risk": _mean(mine),
                "monitored_risk_labelled": _mean(mine[trace.labelled]),
                "bound": _mean(trace.final_bound[i : i + 1]),  # None: no frame defined
                "frames_defined": int((~np.isnan(mine)).sum()),
                "theta_start": float(trace.theta[0, i]),
                "theta_end": float(trace.theta[-1, i]),
                "mu_start": float(self.mu[0, i]),
                "mu_end": float(self.mu[-1, i]),
                "capped_steps": int(trace.capped[i]),
                "windows_above_alpha": {
                    "fixed": float(window_violations(theirs[:, None], [alpha], window)[0]),
                    "monitored": float(window_violations(mine[:, None], [alpha], window)[0]),
                },
                "after_onset": None
                if after is None
                else {"fixed": _mean(theirs[after]), "monitored": _mean(mine[after])},
            }
        labelled = [sum(f.labelled for f in part) for part in (self.fixed, self.monitored)]
        agree = [sum(f.agree for f in part) for part in (self.fixed, self.monitored)]
        return {
            "guarantee": self.guarantee(),
            "constraints": list(self.texts),
            "eta": self.eta,
            "scale": self.scale,
            "delay": self.delay,
            "labelled_share": self.share,
            "start": self.start or "C0 (μ = 0)",
            "base": self.base,
            "mu_max": self.mu_max,
            "space": self.space,
            "frames": len(self.stems),
            "labelled_frames": int(trace.labelled.sum()),
            "shift_onset_frame": None if self.onset is None else self.onset + 1,
            "window": window,
            "requirements": requirements,
            "agreement": {
                "fixed": agree[0] / labelled[0] if labelled[0] else None,
                "monitored": agree[1] / labelled[1] if labelled[1] else None,
            },
            "records": {
                "bytes_per_frame_mean": float(self.record_bytes.mean()) if len(self.stems) else 0,
                "bytes_per_frame_max": int(self.record_bytes.max(initial=0)),
                "kept_share": float(self.kept_pixels.sum() / max(1, labelled[0])),
            },
        }

    def rows(self) -> list[dict]:
        """monitor.csv: one row per frame."""
        trace, fixed = self.trace, self.fixed_losses
        running = running_mean(trace.losses)
        fixed_running = running_mean(fixed)
        rows = []
        for t, stem in enumerate(self.stems):
            row = {"frame": t + 1, "image": stem, "labelled": bool(trace.labelled[t])}
            if self.onset is not None:
                row["shifted"] = t >= self.onset
            for i, text in enumerate(self.texts):
                row |= {
                    f"theta {text}": trace.theta[t, i],
                    f"mu {text}": self.mu[t, i],
                    f"loss {text}": trace.losses[t, i],
                    f"fixed loss {text}": fixed[t, i],
                    f"running risk {text}": running[t, i],
                    f"fixed running risk {text}": fixed_running[t, i],
                    f"bound {text}": trace.bounds[t, i],
                }
            row |= {
                "agreement": _share(self.monitored[t]),
                "fixed agreement": _share(self.fixed[t]),
                "kept pixels": int(self.kept_pixels[t]),
            }
            rows.append(row)
        return rows

    def write(self, results: EvalResults) -> Section:
        record = self.record()
        write_csv(results.output_dir / "monitor.csv", self.rows())
        lines = [
            f"monitor {text}: long-run risk {_cell(r['monitored_risk'])} (fixed "
            f"{_cell(r['fixed_risk'])}) against α = {r['alpha']:.3g}, bound "
            f"{_cell(r['bound'])}; μ {r['mu_start']:.3g} → {r['mu_end']:.3g}"
            for text, r in record["requirements"].items()
        ]
        return Section(
            json={"monitor": record},
            table=self._table(record),
            console=lines,
            jobs=[("evaluation", self._figures(results))],
        )

    def _table(self, record: dict) -> str:
        rows = []
        for text, r in record["requirements"].items():
            rows.append({
                "requirement": text,
                "α": f"{r['alpha']:.3g}",
                "fixed risk": format_value(r["fixed_risk"]),
                "monitored risk": format_value(r["monitored_risk"]),
                "bound": format_value(r["bound"]),
                "windows above α, fixed (%)": format_value(
                    r["windows_above_alpha"]["fixed"], percent=True),
                "windows above α, monitored (%)": format_value(
                    r["windows_above_alpha"]["monitored"], percent=True),
                "μ start → end": f"{r['mu_start']:.3g} → {r['mu_end']:.3g}",
                "capped steps": r["capped_steps"],
            })  # fmt: skip
        agreement = record["agreement"]
        onset = record["shift_onset_frame"]
        return "\n\n".join([
            "",
            f"## Monitored value system (definitions §22): {record['frames']} frames in order, "
            f"η = {self.eta:g} on the {self.scale} scale, labels {self.delay} frame(s) late for "
            f"{record['labelled_frames']} of them; {self.space} matrices; start {record['start']}"
            + ("" if onset is None else f"; shift from frame {onset}"),
            self.guarantee(),
            markdown_table(rows, percent=()),
            f"Agreement with argmax: fixed {format_value(agreement['fixed'])}, monitored "
            f"{format_value(agreement['monitored'])}. Windows of {record['window']} frames. "
            "Per frame: monitor.csv.",
        ]) + "\n"  # fmt: skip

    def _figures(self, results: EvalResults):
        trace = self.trace
        since = "" if self.onset is None else f" from frame {self.onset + 1}"
        shifts = [f"{s}{since}" for s in results.shifts]
        title = f"monitored value system, {figure_subject(results.source, shifts)}"
        return job(
            monitor_figures,
            running_mean(trace.losses),
            running_mean(self.fixed_losses),
            trace.bounds,
            trace.theta[:-1],
            list(self.texts),
            list(self.alphas),
            self.onset,
            self.scale,
            title,
        )


def _mean(values: np.ndarray) -> float | None:
    defined = values[~np.isnan(values)]
    return float(defined.mean()) if len(defined) else None


def _share(counts: FrameCounts) -> float:
    return counts.agree / counts.labelled if counts.labelled else float("nan")


def _cell(value: float | None) -> str:
    return "—" if value is None else f"{value:.4f}"
