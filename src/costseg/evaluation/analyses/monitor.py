"""``--monitor_require``: requirements kept on the reported images as a stream of frames, in
their order (docs/definitions.md §22).

θ_t depends on the frames before t, and under ``torchrun`` a process sees every
``world_size``-th image. So each image leaves an exact record while it passes
(:func:`~costseg.calibration.stream_records.record_frame`: the pixels every matrix the monitor
can reach decides alike, counted once; the others kept), written to a file of the run while the
image passes; the records' names come together in the images' order, and the stream is walked
once at the end, one record read at a time (:func:`~costseg.calibration.monitor.run_stream`):
the same θ sequence in one process, several, or the Python API. The fixed matrix (the start's)
is counted on the same records.
"""

from __future__ import annotations

import shutil

import numpy as np
import torch

from costseg.calibration.monitor import labelled_frames, run_stream, to_mu
from costseg.calibration.stream_records import FrameRecord, record_frame
from costseg.evaluation.analyses import Analysis, Seen
from costseg.evaluation.processes import barrier, in_image_order, rank
from costseg.evaluation.settings import MonitorSettings
from costseg.metrics.monitor import Monitor
from costseg.report.monitor import FrameCounts, StreamOutcome

RECORDS = "monitor_records"
"""The folder of the run that holds each frame's record while the images pass (one file a
frame, so that a long stream at full resolution does not stay in memory); removed once walked."""


class Monitored(Analysis):
    settings: MonitorSettings

    def start(self) -> None:
        s = self.settings
        self.monitor = Monitor(s.requirements, s.eta, base=s.base, start=s.start, scale=s.scale,
                               mu_max=s.mu_max, space=s.space)  # fmt: skip
        self.space = self.monitor.space()
        self.classes = [t.cls for t in self.monitor.requirements.constraints]
        self.folder = self.context.plan.output_dir / RECORDS
        self.folder.mkdir(exist_ok=True)
        self.records: list = []  # (position, (stem, file, bytes, kept pixels)) of this process's

    def process(self, seen: Seen) -> None:
        labels = seen.batch.labels
        roi = None if seen.roi is None else seen.roi.expand_as(labels)
        with torch.inference_mode():
            for b, position in enumerate(seen.positions):
                frame = record_frame(seen.probs[b], labels[b], None if roi is None else roi[b],
                                     self.space, self.classes)  # fmt: skip
                file = self.folder / f"{position:06d}.pt"
                frame.save(file)
                self.records.append(
                    (position, (seen.batch.stems[b], file, frame.nbytes, frame.kept_pixels))
                )

    def gather(self) -> None:
        self.records = in_image_order(self.records)

    def result(self) -> StreamOutcome:
        s, monitor = self.settings, self.monitor
        stems, files, nbytes, kept = zip(*self.records, strict=True) if self.records else [()] * 4
        fixed, fixed_counts, monitored = monitor.fixed, [], []

        def losses(t: int, theta: np.ndarray) -> np.ndarray:
            frame = FrameRecord.load(files[t])  # one frame in memory at a time
            fixed_counts.append(frame_counts(monitor, frame, fixed))
            monitored.append(frame_counts(monitor, frame, monitor.matrix(theta)))
            return monitored[-1].losses

        labelled = labelled_frames(len(files), s.labelled, s.seed)
        trace = run_stream(losses, len(files), monitor.controller, s.delay, labelled)
        barrier()  # every process has walked the records
        if rank() == 0:
            shutil.rmtree(self.folder)
        shifted = bool(self.context.plan.shifts)
        return StreamOutcome(
            texts=s.requirements,
            alphas=monitor.requirements.alphas,
            eta=s.eta,
            scale=s.scale,
            delay=s.delay,
            share=s.labelled,
            start=s.start,
            base=s.base,
            mu_max=s.mu_max,
            space=s.space,
            stems=list(stems),
            trace=trace,
            mu=to_mu(trace.theta, s.scale),
            fixed=fixed_counts,
            monitored=monitored,
            onset=s.shift_onset if shifted and s.shift_onset else None,
            record_bytes=np.array(nbytes),
            kept_pixels=np.array(kept),
        )


def frame_counts(monitor: Monitor, frame: FrameRecord, matrix: torch.Tensor) -> FrameCounts:
    """One frame's losses and agreement under ``matrix``."""
    counts = frame.counts(matrix)
    losses = monitor.requirements.losses(counts.confusion)[0].numpy()
    return FrameCounts(losses, int(counts.agree[0]), int(counts.confusion[0, 0].sum()))


ANALYSIS = Monitored
