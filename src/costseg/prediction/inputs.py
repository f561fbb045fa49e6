"""What ``predict.py --input`` names: an image, a folder of images, or a video (docs/usage.md).

Every file is checked before the network loads: an unreadable file, a folder without images or
a missing path is a ValueError (or FileNotFoundError) whose one line names it. Images come as
(H, W, 3) uint8 RGB with their EXIF orientation applied; videos frame by frame (PyAV, the
``video`` extra), never all in memory.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm")


@dataclass(frozen=True)
class VideoInfo:
    """A checked video: its frame rate and frame count (None when the container does not say)."""

    path: Path
    rate: Fraction
    frames: int | None
    size: tuple[int, int]  # (H, W)


@dataclass(frozen=True)
class Inputs:
    """The checked inputs: images (in name order) or one video."""

    images: list[Path]
    video: VideoInfo | None = None

    def __len__(self) -> int:
        return len(self.images) if self.video is None else 1


def find_inputs(path: str | Path) -> Inputs:
    """Check ``--input`` and list what it names.

    Raises:
        FileNotFoundError: no such file or folder.
        ValueError: an unreadable image or video, a file of another kind, or a folder without
            images (one line naming the path).

    >>> find_inputs("no/such.png")
    Traceback (most recent call last):
    ...
    FileNotFoundError: --input not found: no/such.png
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"--input not found: {path}")
    if path.is_dir():
        images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not images:
            kinds = ", ".join(s.lstrip(".") for s in IMAGE_SUFFIXES)
            raise ValueError(f"--input folder {path} holds no images ({kinds})")
        stems = [p.stem for p in images]
        if len(set(stems)) != len(stems):
            twice = next(s for s in stems if stems.count(s) > 1)
            raise ValueError(f"--input folder {path} holds two images named {twice}.*")
        for image in images:
            check_image(image)
        return Inputs(images)
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return Inputs([path], probe_video(path))
    if suffix not in IMAGE_SUFFIXES:
        kinds = ", ".join(s.lstrip(".") for s in IMAGE_SUFFIXES + VIDEO_SUFFIXES)
        raise ValueError(f"--input {path} is neither an image nor a video ({kinds})")
    check_image(path)
    return Inputs([path])


def check_image(path: Path) -> None:
    """ValueError naming ``path`` unless PIL reads it as an image (header and data checked)."""
    try:
        with Image.open(path) as image:
            image.verify()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise ValueError(f"cannot read image {path}: {_reason(err)}") from None


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file, upright (EXIF orientation), grey/RGBA → RGB."""
    try:
        with Image.open(path) as image:
            image = ImageOps.exif_transpose(image)
            return np.array(image.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise ValueError(f"cannot read image {path}: {_reason(err)}") from None


def _av():
    try:
        import av
    except ImportError:
        raise ValueError(
            "reading videos needs PyAV: pip install 'costseg[video]' (or pip install av)"
        ) from None
    return av


def probe_video(path: Path) -> VideoInfo:
    """Open a video and decode its first frame; ValueError naming it if that fails."""
    av = _av()
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ValueError(f"cannot read video {path}: it holds no video stream")
            stream = container.streams.video[0]
            first = next(container.decode(stream), None)
            if first is None:
                raise ValueError(f"cannot read video {path}: it holds no frames")
            rate = stream.average_rate or stream.guessed_rate or Fraction(25)
            return VideoInfo(
                path, Fraction(rate), stream.frames or None, (first.height, first.width)
            )
    except av.FFmpegError as err:
        raise ValueError(f"cannot read video {path}: {_reason(err)}") from None


def video_frames(path: Path) -> Iterator[np.ndarray]:
    """(H, W, 3) uint8 RGB frames of a video, one at a time."""
    av = _av()
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            for frame in container.decode(stream):
                yield frame.to_ndarray(format="rgb24")
    except av.FFmpegError as err:
        raise ValueError(f"cannot read video {path}: {_reason(err)}") from None


def _reason(err: BaseException) -> str:
    return (str(err).strip().splitlines() or [type(err).__name__])[0]
