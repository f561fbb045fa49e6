"""Ensembles (``docs/definitions.md §13``): the mean of several sources' probabilities.

``--ckpt_path A B`` and ``--network X Y`` (together too: the ``--ckpt_path`` members, then the
``--network`` ones) name the members; each runs with the inference protocol and Monte-Carlo
dropout given, and the ensemble's map is the mean of the members' probabilities, each member
weighing the same. A single source is not wrapped: a one-member ensemble is that member.

The runs of the uncertainty maps are the members; with Monte-Carlo dropout, every pass of every
member (each member's map is its mean over its passes, and its passes' mean entropy is pooled).
Every member is seeded alike (the seed and the image names), so identical members give identical
runs. The ensemble's dataset, priors and default output folder are its first costseg member's
(none: as for any other network, ``--data_root`` and the dataset's training labels).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from costseg.checkpoints import find_checkpoint
from costseg.networks import check_spec
from costseg.networks.protocols import Protocol, with_protocol
from costseg.networks.sources import Source, open_source
from costseg.networks.uncertainty import RunAverage


class Ensemble(nn.Module):
    """A network whose output is the mean of its members' probabilities.

    Args:
        members: the sources, each already run as its protocol says.

    Example:
        >>> from costseg.networks.base import ImageNetwork
        >>> net = ImageNetwork(torch.nn.Conv2d(3, 4, 1))
        >>> member = Source("network", {"network": "a"}, network=net)
        >>> images = torch.zeros(1, 3, 2, 2, dtype=torch.uint8)
        >>> bool(torch.equal(Ensemble([member])(images), net(images).softmax(1)))
        True
    """

    def __init__(self, members: Sequence[Source]) -> None:
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one member")
        self.members = list(members)
        self.networks = nn.ModuleList([m.network for m in self.members if m.network is not None])

    def forward(self, images: Tensor, names: Sequence[str] = ()) -> Tensor:
        """(B, 3, H, W) uint8 images named ``names`` → (B, N, H, W) float32 probabilities."""
        return self.average(images, names, keep_entropy=False).mean

    def average(
        self, images: Tensor, names: Sequence[str] = (), keep_entropy: bool = True
    ) -> RunAverage:
        """The members' mean probabilities and (``keep_entropy``) the mean entropy of their runs.

        Raises:
            ValueError: members that give different numbers of classes.
        """
        runs, first = RunAverage(keep_entropy), None
        for m, member in enumerate(self.members):
            if keep_entropy:
                scores, expected = member.scores_and_entropy(images, list(names))
            else:
                scores, expected = member.scores(images, list(names)), None
            probs = scores if member.kind == "probs" else scores.softmax(1)
            first = probs.shape[1] if first is None else first
            if probs.shape[1] != first:
                raise ValueError(
                    f"ensemble members disagree on the classes: member 1 gives {first}, "
                    f"member {m + 1} ({member_name(member)}) gives {probs.shape[1]}"
                )
            runs.add(probs, expected)
        return runs

    def describe(self) -> str:
        """What the probabilities are, for every output."""
        parts = [
            f"{m + 1}: {member.probabilities or 'softmax of the logits'}"
            for m, member in enumerate(self.members)
        ]
        return (
            f"ensemble: mean probabilities of {len(self.members)} members ({'; '.join(parts)}); "
            "uncertainty over the members' runs"
        )


def member_name(source: Source) -> str:
    """The spec a member was opened from (``costseg:PATH``, ``vainf:PATH``, ...)."""
    return str(source.description.get("network", "?"))


def member_specs(ckpt_path, network) -> list[tuple[str | None, str | None]]:
    """``(ckpt_path, network)`` of each member, the ``--ckpt_path`` ones first; one
    ``(None, None)`` (the newest checkpoint) when neither is given. A single string counts as a
    one-member list.

    >>> member_specs(["a.ckpt", "b.ckpt"], "vainf:c.pth")
    [('a.ckpt', None), ('b.ckpt', None), (None, 'vainf:c.pth')]
    >>> member_specs(None, None)
    [(None, None)]
    """
    paths = [ckpt_path] if isinstance(ckpt_path, str) else list(ckpt_path or [])
    networks = [network] if isinstance(network, str) else list(network or [])
    specs = [(p, None) for p in paths] + [(None, n) for n in networks]
    return specs or [(None, None)]


def open_sources(
    ckpt_path: str | Sequence[str] | None,
    network: str | Sequence[str] | None,
    probs: str | None,
    device: torch.device,
    protocol: Protocol,
    passes: int | None,
    seed: int,
) -> Source:
    """The source the options name, run as ``protocol`` says with ``passes`` of Monte-Carlo
    dropout: saved probabilities, one network, or the ensemble of several.

    Raises:
        ValueError: as :func:`~costseg.networks.sources.open_source` and
            :func:`~costseg.networks.protocols.with_protocol` for any member.
        FileNotFoundError: a member's file does not exist.
    """
    specs = [(None, None)] if probs is not None else member_specs(ckpt_path, network)
    for path, spec in specs:  # every member's file, before any network is loaded
        if spec is not None:
            check_spec(spec)
        elif path is not None:
            find_checkpoint(path)
    members = [
        with_protocol(open_source(path, spec, probs, device), protocol, passes, seed)
        for path, spec in specs
    ]
    source = members[0] if len(members) == 1 else ensemble_source(members, protocol, passes, seed)
    source.description["uncertainty"] = uncertainty_note(source.network)
    return source


def uncertainty_note(network: nn.Module | None) -> str:
    """What the uncertainty maps of a source's network are over, for every output.

    >>> uncertainty_note(None).split("; ")[1]
    'one run: no mutual information'
    """
    text = "entropy in nats of the probabilities before calibration and float16 rounding"
    runs = _runs(network)
    return f"{text}; one run: no mutual information" if runs is None else f"{text}; {runs}"


def _runs(network: nn.Module | None) -> str | None:
    """The runs of the mutual information, or None for a single run."""
    if isinstance(network, Ensemble):
        inner = _runs(network.members[0].network)
        count = len(network.members)
        if count == 1:
            return inner
        if inner is None:
            return f"mutual information over the {count} members"
        each = inner.removeprefix("mutual information over ")
        return f"mutual information over {each} of each of the {count} members"
    passes = getattr(network, "passes", None)  # MCDropout
    mc_dropout = getattr(network, "mc_dropout", None)  # TestTimeAugmentation
    if mc_dropout is not None:
        passes = mc_dropout[0].passes
    if not passes or passes < 2:
        return None
    views = "" if mc_dropout is None else f" (each the mean over the {len(network.views)} views)"
    return f"mutual information over the {passes} Monte-Carlo dropout passes{views}"


def ensemble_source(
    members: Sequence[Source], protocol: Protocol, passes: int | None, seed: int
) -> Source:
    """The source of the ensemble of ``members`` (each run with ``protocol`` and ``passes``)."""
    net = Ensemble(members)
    names = [member_name(m) for m in members]
    description: dict = {
        "network": "ensemble: " + " + ".join(names),
        "members": [m.description for m in members],
        **protocol.describe(),
    }
    if passes is not None:
        description["mc_dropout"] = {"passes": passes, "seed": seed}
    costseg = [(k, m) for k, m in enumerate(members) if m.run_dir is not None]
    first = costseg[0][1] if costseg else None
    if first is not None:
        k = costseg[0][0]
        priors = first.description.get("priors")
        description["priors"] = {"member": k + 1, "priors": priors}
    return Source(
        "probs",
        description,
        network=net,
        priors=None if first is None else first.priors,
        data_config=None if first is None else first.data_config,
        run_dir=None if first is None else first.run_dir,
        probabilities=net.describe(),
    )
