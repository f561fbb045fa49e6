"""What ``predict.py --input`` names: images, folders of images (read recursively) and videos,
mixed (docs/predict.md).

Every file is checked before the network loads: an unreadable file, a folder without images or
a missing path is a ValueError (or FileNotFoundError) whose one line names it. Each image or
video gets a name, its path relative to the deepest folder holding every input, without the
suffix (``frankfurt/frankfurt_000000_000294_leftImg8bit`` for ``--input leftImg8bit/val``), so
the outputs keep the inputs' sub-folder layout and two images of the same file name in different
sub-folders never share an output. Images come as (H, W, 3) uint8 RGB with their EXIF orientation
applied; videos frame by frame (PyAV, the ``video`` extra), never all in memory.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
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
class Item:
    """One checked image or video and the name its outputs take (a relative path, no suffix)."""

    path: Path
    name: str
    video: VideoInfo | None = None


@dataclass(frozen=True)
class Inputs:
    """The checked inputs: images and videos, in the order given (a folder's in name order)."""

    items: list[Item]
    paths: list[Path]  # as given

    @property
    def images(self) -> list[Item]:
        return [i for i in self.items if i.video is None]

    @property
    def videos(self) -> list[Item]:
        return [i for i in self.items if i.video is not None]

    def __len__(self) -> int:
        return len(self.items)


def find_inputs(paths: str | Path | Sequence[str | Path]) -> Inputs:
    """Check ``--input`` (one path or several) and list and name what it holds.

    Raises:
        FileNotFoundError: no such file or folder.
        ValueError: an unreadable image or video, a file of another kind, a folder without
            images, or two images that would get the same name (one line naming the paths).

    >>> find_inputs(["no/such.png"])
    Traceback (most recent call last):
    ...
    FileNotFoundError: --input not found: no/such.png
    """
    paths = [Path(paths)] if isinstance(paths, (str, os.PathLike)) else [Path(p) for p in paths]
    files = [f for path in paths for f in _files(path)]
    files = list(dict.fromkeys(map(_absolute, files)))  # a file named twice is read once
    roots = [_absolute(p) if p.is_dir() else _absolute(p).parent for p in paths]
    base = Path(os.path.commonpath(roots))
    items, owners = [], {}
    for file in files:
        name = file.relative_to(base).with_suffix("").as_posix()
        if name in owners:
            raise ValueError(
                f"--input {owners[name]} and {file} would both be written as {name}: "
                "rename one, or give them to separate runs"
            )
        owners[name] = file
        video = probe_video(file) if file.suffix.lower() in VIDEO_SUFFIXES else None
        if video is None:
            check_image(file)
        items.append(Item(file, name, video))
    return Inputs(items, paths)


def _absolute(path: Path) -> Path:
    return Path(os.path.abspath(path))  # without "..", unlike Path.absolute


def _files(path: Path) -> list[Path]:
    """The images of a folder (recursively, in name order) or ``path`` itself."""
    if not path.exists():
        raise FileNotFoundError(f"--input not found: {path}")
    if path.is_dir():
        images = sorted(
            p for p in path.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
        )
        if not images:
            kinds = ", ".join(s.lstrip(".") for s in IMAGE_SUFFIXES)
            raise ValueError(
                f"--input folder {path} holds no images ({kinds}), nor do its sub-folders"
            )
        return images
    if path.suffix.lower() not in IMAGE_SUFFIXES + VIDEO_SUFFIXES:
        kinds = ", ".join(s.lstrip(".") for s in IMAGE_SUFFIXES + VIDEO_SUFFIXES)
        raise ValueError(f"--input {path} is neither an image nor a video ({kinds})")
    return [path]


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
