"""What a designed cost file was certified for (docs/definitions.md §20): the probability source
named with its file's SHA-256 in the certificate's header, and a note when an evaluation uses
the file with probabilities from another source. Light: read before a network loads."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from pathlib import Path

CERTIFIED_FOR = "certified for: "
"""How the header's line naming the source begins (after the comment's ``# ``)."""


def fingerprint(source: dict) -> str:
    """The probability source of a description, with the SHA-256 (its first 16 hex digits) of
    the file behind it where there is one.

    >>> fingerprint({"probs": "no/such/folder"})
    'no/such/folder'
    """
    if "members" in source:
        return "ensemble of " + ", ".join(fingerprint(m) for m in source["members"])
    spec = str(source.get("network") or source.get("probs") or source)
    path = Path(spec.split(":", 1)[-1].split("?")[0]) if ":" in spec else Path(spec)
    if not path.is_file():
        return spec
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return f"{spec} (sha256 {digest.hexdigest()[:16]})"


REQUIREMENT = "requirement "
"""How each of the header's lines of a requirement begins: then its text, then ``: ``."""


def header_lines(path: str | Path) -> list[str]:
    """A cost file's leading comment lines, each wrapped line joined to the one it continues
    (none: an unreadable file, or no header)."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    header: list[str] = []
    for line in lines:
        if not line.startswith("#"):
            break
        text = line.removeprefix("#").removeprefix(" ")
        if text.startswith("  ") and header:  # a wrapped line goes on
            header[-1] += " " + text.strip()
        else:
            header.append(text.strip())
    return header


def certified_source(path: str | Path) -> str | None:
    """The source a cost file's header says it was certified for, or None (no such line).

    >>> certified_source("no/such.yaml") is None
    True
    """
    for text in header_lines(path):
        if text.startswith(CERTIFIED_FOR):
            return text.removeprefix(CERTIFIED_FOR).split(";")[0]
    return None


def certified_requirements(path: str | Path) -> list[str]:
    """The requirements a designed cost file's header certifies (``person:roi1:recall>=0.8``),
    in its order; none for any other file."""
    return [
        text.removeprefix(REQUIREMENT).split(": ")[0]
        for text in header_lines(path)
        if text.startswith(REQUIREMENT)
    ]


def same_source(first: str, second: str) -> bool:
    """Whether two fingerprints name the same source: the same hashes where both have them
    (a file moved keeps its certificate), else the same text.

    >>> same_source("costseg:a.ckpt (sha256 12ab)", "costseg:b/a.ckpt (sha256 12ab)")
    True
    """
    hashes = [re.findall(r"sha256 ([0-9a-f]+)", text) for text in (first, second)]
    return hashes[0] == hashes[1] if all(hashes) else first == second


def certificate_notes(costs: Sequence[str], source: dict) -> list[str]:
    """A note per designed cost file of ``costs`` certified for another probability source
    than ``source`` (an evaluation's description): its certificate does not carry over."""
    notes, ours = [], None
    for cost in costs:
        theirs = certified_source(cost) if str(cost).endswith((".yaml", ".yml")) else None
        if theirs is None:
            continue
        ours = ours or fingerprint(source)
        if not same_source(theirs, ours):
            notes.append(
                f"note: {cost} was certified for {theirs}; these probabilities come from "
                f"{ours}: its certificate holds for that source only"
            )
    return notes
