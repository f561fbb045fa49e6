"""The one atomic writer: every file costseg writes goes through :class:`AtomicFile`.

A file is written under a temporary name in its destination folder and renamed over the
destination (``os.replace``) only once complete, so a reader never sees a half-written file,
even if the process is killed mid-write; a failed write leaves nothing behind. An ``OSError``
while writing names the destination, not the temporary file.

>>> import tempfile
>>> with tempfile.TemporaryDirectory() as d:
...     with AtomicFile(Path(d) / "a" / "b.txt") as tmp:
...         _ = tmp.write_text("hi")
...     sorted(p.name for p in (Path(d) / "a").iterdir()), (Path(d) / "a" / "b.txt").read_text()
(['b.txt'], 'hi')
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path


class AtomicFile:
    """A temporary file beside ``path`` that becomes ``path`` on :meth:`commit`.

    As a context manager it yields the temporary path, commits when the block ends normally and
    discards the file when it raises. The temporary name keeps ``path``'s suffix, for writers
    that choose a format by it (PyAV).

    Args:
        path: the destination; its parent folders are created.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(
            f".{self.path.stem}.{uuid.uuid4().hex[:8]}.tmp{self.path.suffix}"
        )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.tmp.touch(exist_ok=False)  # a name of its own; the umask's permissions
        except OSError as error:
            self.name(error)
            raise

    def commit(self) -> Path:
        """Rename the finished temporary file to the destination; return the destination."""
        try:
            os.replace(self.tmp, self.path)
        except OSError as error:
            self.discard()
            self.name(error)
            raise
        return self.path

    def discard(self) -> None:
        """Remove the temporary file (the destination is left as it was)."""
        self.tmp.unlink(missing_ok=True)

    def name(self, error: OSError) -> None:
        """Make ``error`` name the destination where it names no file or the temporary one."""
        if error.filename is None or str(error.filename) == str(self.tmp):
            error.filename = str(self.path)

    def __enter__(self) -> Path:
        return self.tmp

    def __exit__(self, kind, error, traceback) -> None:
        if kind is None:
            self.commit()
            return
        self.discard()
        if isinstance(error, OSError):
            self.name(error)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_bytes(Path(d) / "x.bin", b"abc").read_bytes()
    b'abc'
    """
    with AtomicFile(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)
