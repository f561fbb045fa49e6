"""The one atomic writer: a finished write replaces the file, a failed one leaves the old file and
no temporary file, and an OSError names the destination."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from costseg.atomic import AtomicFile, write_bytes


def test_write_bytes_creates_folders_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "f.bin"
    write_bytes(path, b"one")
    write_bytes(path, b"two")
    assert path.read_bytes() == b"two"
    assert [p.name for p in path.parent.iterdir()] == ["f.bin"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "f.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), AtomicFile(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed mid-write")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def test_the_temporary_file_keeps_the_suffix_and_lies_beside(tmp_path: Path) -> None:
    file = AtomicFile(tmp_path / "v.mp4")
    assert file.tmp.parent == tmp_path and file.tmp.suffix == ".mp4"
    assert not (tmp_path / "v.mp4").exists()  # nothing at the destination until the commit
    file.tmp.write_bytes(b"x")
    assert file.commit() == tmp_path / "v.mp4"
    assert (tmp_path / "v.mp4").read_bytes() == b"x" and not file.tmp.exists()
    other = AtomicFile(tmp_path / "w.mp4")
    other.discard()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


@pytest.mark.parametrize("named", [None, "tmp"])
def test_an_oserror_names_the_destination(tmp_path: Path, named: str | None) -> None:
    """A full disk: the error (no file name, or the temporary one) says which file failed."""
    path = tmp_path / "results.json"
    with pytest.raises(OSError) as caught, AtomicFile(path) as tmp:
        raise OSError(errno.ENOSPC, "No space left on device", named and str(tmp))
    assert str(caught.value) == f"[Errno 28] No space left on device: '{path}'"
    assert list(tmp_path.iterdir()) == []


def test_a_folder_that_cannot_be_made_is_named(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError) as caught:
        write_bytes(tmp_path / "file" / "x.bin", b"")
    assert str(tmp_path / "file") in str(caught.value)


def test_files_get_the_umask_permissions(tmp_path: Path) -> None:
    """As a plain ``open`` would give them (a private temporary file would leave 0o600)."""
    import os

    old = os.umask(0o022)
    try:
        path = write_bytes(tmp_path / "shared.png", b"x")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644
