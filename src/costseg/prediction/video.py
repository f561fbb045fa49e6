"""Videos written frame by frame (PyAV): same frame count and rate as the input.

Each file is written under a temporary name and renamed once complete, so an interrupted run
leaves no video that looks finished.
"""

from __future__ import annotations

import contextlib
from fractions import Fraction
from pathlib import Path

import numpy as np

from costseg.atomic import AtomicFile

CODECS = ("libx264", "h264", "mpeg4")


class VideoWriter:
    """An H.264 (or MPEG-4) video of (H, W, 3) uint8 frames, opened on the first frame.

    Args:
        path: the finished file (``.mp4``).
        rate: frames per second (a Fraction keeps 30000/1001 exact).
    """

    def __init__(self, path: Path, rate: Fraction) -> None:
        self.path, self.rate = path, rate
        self.file: AtomicFile | None = None
        self.container = self.stream = None
        self.count = 0

    def _open(self, height: int, width: int) -> None:
        import av

        self.file = AtomicFile(self.path)
        self.container = av.open(str(self.file.tmp), "w")
        codec = next(c for c in CODECS if c in av.codecs_available)
        self.stream = self.container.add_stream(codec, rate=self.rate)
        self.stream.width, self.stream.height = width, height
        self.stream.pix_fmt = "yuv420p"
        self.stream.time_base = 1 / self.rate
        if codec == "libx264":
            self.stream.options = {"crf": "18", "preset": "veryfast"}

    def write(self, frame: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 RGB frame; odd sizes are padded by one row / column."""
        import av

        pad = ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0))
        frame = np.pad(frame, pad, mode="edge") if any(p[1] for p in pad[:2]) else frame
        if self.container is None:
            self._open(*frame.shape[:2])
        out = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
        out.pts = self.count
        out.time_base = self.stream.time_base
        self.container.mux(self.stream.encode(out))
        self.count += 1

    def close(self) -> None:
        """Flush the encoder and move the file to its name."""
        if self.container is None:
            return
        self.container.mux(self.stream.encode(None))
        self.container.close()
        self.container = None
        self.file.commit()

    def abandon(self) -> None:
        """Drop an unfinished file."""
        if self.container is not None:
            with contextlib.suppress(Exception):  # the file is removed either way
                self.container.close()
            self.container = None
        if self.file is not None:
            self.file.discard()
