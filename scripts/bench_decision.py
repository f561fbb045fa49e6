"""Speed of the decision layer at Cityscapes scale, as ratios measured side by side in one run.

    python scripts/bench_decision.py [--repeats 5] [--size 1024 2048] [--threads N]
        [--counts] [--candidates 1000 [--share 1.0]]

On (1, 19, H, W) float32 probabilities (softmax of smooth random logits, the recipe of
``scripts/bench.py``), on the CPU and, when there is one, on the GPU: one read pass ``p.sum()``,
``torch.argmax(p, 1)``, single-rule ``decide`` (egoistic, and egoistic with a defer row of
:data:`DEFER` times its mean off-diagonal cost, docs/definitions.md §14), ``decide`` of a regional
value system (docs/definitions.md §21: :func:`regional_stack`'s five matrices on the uint8
geometric RoI map, ids 1 to 4, each pixel of RoI r decided with matrix r; also the egoistic
matrix times 1 … 5, whose regional pass must give egoistic's labels; on the CPU also the fused
count pass of a search, ``count_decisions`` on pixels prepared once with :func:`labelled`, of the
five matrices against egoistic alone) and ``decide_mixtures``
over the 66-point barycentric grid (robotistic / altruistic / egoistic vertices, unscaled), on the
CPU also without numba's kernels. Each timing is the best of several repeats after a warm-up; every
ratio compares timings of the same run. The target ratios are also given as the median over
rounds that time both sides back to back (a machine whose speed drifts moves both alike).

``--counts``: the fused decide-and-count pass of a search (``count_decisions`` on pixels prepared
once, every pixel labelled, five RoI bands) against ``decide`` alone on the same probabilities,
at ``--size`` and at the demo's image size (8 images of 128 × 256), for the altruistic matrix and
a generic dense one, and the pass with a defer row against itself without. ``--candidates K``:
the wall time of K random dense matrices scored on the demo's held-out images (labels: the toy val
split's second half; probabilities: the demo model's when ``--ckpt`` is given, else smooth random
ones of the same shape), on ``--share`` of each image's labelled pixels.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import torch

from costseg.cli import parse_options
from costseg.costs import barycentric_grid, load_cost, with_defer
from costseg.data.priors import geometric_roi_map
from costseg.decision import (
    DEFERRED,
    count_decisions,
    decide,
    decide_mixtures,
    prepare_counts,
    subsample,
)
from costseg.options import option
from costseg.values import share, whole_number

VERTICES = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
DEFER = 0.5  # × the egoistic matrix's mean off-diagonal cost: about 5 % of pixels deferred


def egoistic_with_defer() -> torch.Tensor:
    """The egoistic matrix with a defer row of ``DEFER`` times its mean off-diagonal cost."""
    cost, n = VERTICES[2], VERTICES.shape[-1]
    return with_defer(cost, DEFER * cost.sum().item() / (n * n - n))


def regional_stack(scaled: bool = False) -> torch.Tensor:
    """Five distinct matrices of the egoistic kind, each as fast to decide alone (measured): the
    egoistic matrix with person's column (the cost of missing a person) times 1 … 5; with
    ``scaled``, the whole matrix times 1 … 5 (egoistic's decisions everywhere: the ratio is then
    the regional pass's own cost)."""
    factors = torch.arange(1, 6, dtype=torch.float64)
    if scaled:
        return VERTICES[2] * factors[:, None, None]
    stack = VERTICES[2].expand(5, -1, -1).clone()
    person = 11
    stack[:, :, person] *= factors[:, None]
    return stack


def best_time(fn: Callable[[], object], repeats: int, sync: Callable[[], object]) -> float:
    """Best wall time in seconds of ``repeats`` calls, after one warm-up call."""
    fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return min(times)


def paired_ratio(
    slow: Callable[[], object], fast: Callable[[], object], rounds: int, sync: Callable[[], object]
) -> float:
    """Median over ``rounds`` of ``slow``'s time ÷ ``fast``'s, each round timing one call of
    each back to back (in alternating order)."""
    ratios = []
    for r in range(rounds):
        times, order = {}, (("slow", slow), ("fast", fast))
        for name, fn in order if r % 2 else order[::-1]:
            start = time.perf_counter()
            fn()
            sync()
            times[name] = time.perf_counter() - start
        ratios.append(times["slow"] / times["fast"])
    return statistics.median(ratios)


def probabilities(shape: tuple[int, int, int, int], device: str) -> torch.Tensor:
    """Softmax of smooth random logits: confident almost everywhere, unsure near borders."""
    gen = torch.Generator().manual_seed(0)
    b, n, h, w = shape
    coarse = torch.randn(b, n, h // 16, w // 16, generator=gen) * 6
    logits = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear")
    return logits.softmax(1).to(device)


def labelled(probs: torch.Tensor) -> torch.Tensor:
    """A plausible label map: the argmax of ``probs``, void (255) on the bottom tenth of each
    image (Cityscapes' ego vehicle)."""
    labels = probs.argmax(1)
    labels[:, labels.shape[1] - labels.shape[1] // 10 :] = 255
    return labels


def bench(device: str, shape: tuple[int, int, int, int], repeats: int) -> None:
    """Print the timings and ratios on one device."""
    probs = probabilities(shape, device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    grid = barycentric_grid(0.1)
    run_sum, run_decide = (lambda: probs.sum()), (lambda: decide(probs, VERTICES[2]))
    deferring = egoistic_with_defer().to(device)
    run_defer = lambda: decide(probs, deferring)  # noqa: E731
    run_mix = lambda: decide_mixtures(probs, VERTICES, grid)  # noqa: E731
    roi = geometric_roi_map(shape[2:]).to(device, torch.uint8)  # the graph's RoI map is uint8
    stack, scaled = regional_stack().to(device), regional_stack(scaled=True).to(device)
    run_regional = lambda: decide(probs, stack, roi=roi)  # noqa: E731
    run_scaled = lambda: decide(probs, scaled, roi=roi)  # noqa: E731
    t_sum = best_time(run_sum, repeats, sync)
    t_argmax = best_time(lambda: probs.argmax(1), repeats, sync)
    t_decide = best_time(run_decide, repeats, sync)
    t_defer = best_time(run_defer, repeats, sync)
    deferred = (run_defer() == DEFERRED).float().mean().item()
    t_regional = best_time(run_regional, repeats, sync)
    t_mix = best_time(run_mix, max(3, repeats // 2), sync)
    rounds = 2 * repeats + 1
    paired_decide = paired_ratio(run_decide, run_sum, rounds, sync)
    paired_mix = paired_ratio(run_mix, run_decide, rounds, sync)
    paired_defer = paired_ratio(run_defer, run_decide, rounds, sync)
    paired_regional = paired_ratio(run_regional, run_decide, rounds, sync)
    paired_scaled = paired_ratio(run_scaled, run_decide, rounds, sync)
    if device == "cpu":  # the fused count pass (a search's), regional against one matrix
        prepared = prepare_counts(probs, labelled(probs), roi)
        count_regional = lambda: count_decisions(prepared, stack)  # noqa: E731
        count_one = lambda: count_decisions(prepared, VERTICES[2])  # noqa: E731
        t_count_regional = best_time(count_regional, repeats, sync)
        t_count_one = best_time(count_one, repeats, sync)
        paired_count = paired_ratio(count_regional, count_one, rounds, sync)
    fine = barycentric_grid(0.05)
    t_fine = best_time(lambda: decide_mixtures(probs, VERTICES, fine), 1, sync)
    t_ops = t_decide_ops = None
    if device == "cpu":  # the same without numba's kernels: the "torch" path
        t_decide_ops = best_time(lambda: decide(probs, VERTICES[2], path="torch"), repeats, sync)
        t_ops = best_time(lambda: decide_mixtures(probs, VERTICES, grid, path="torch"), 1, sync)
    threads = f", {torch.get_num_threads()} threads" if device == "cpu" else ""
    print(f"{device}{threads}, probabilities {tuple(shape)} float32:")
    print(f"  p.sum() (one read pass)        {1e3 * t_sum:8.3f} ms")
    print(f"  torch.argmax(p, 1)             {1e3 * t_argmax:8.3f} ms")
    print(f"  decide (egoistic)              {1e3 * t_decide:8.3f} ms")
    if t_decide_ops:
        print(f"  same, tensor ops               {1e3 * t_decide_ops:8.3f} ms   (without numba)")
    share = f"({100 * deferred:.1f} % deferred)"
    print(f"  decide (egoistic + defer row)  {1e3 * t_defer:8.3f} ms   {share}")
    print(f"  decide (RoI map, 5 matrices)   {1e3 * t_regional:8.3f} ms")
    print(f"  decide_mixtures, {len(grid)} points    {1e3 * t_mix:8.3f} ms")
    print(f"  decide_mixtures, {len(fine)} points   {1e3 * t_fine:8.3f} ms")
    if t_ops:
        print(f"  same, {len(grid)} points, tensor ops  {1e3 * t_ops:8.3f} ms   (without numba)")
    paired = f"median of {rounds} rounds back to back"
    print(f"  decide / p.sum()               {t_decide / t_sum:8.2f}   (target <= 5)")
    print(f"  same, {paired}: {paired_decide:.2f}")
    print(f"  decide / argmax                {t_decide / t_argmax:8.2f}")
    print(f"  decide with / without defer    {t_defer / t_decide:8.2f}")
    print(f"  same, {paired}: {paired_defer:.2f}")
    print(f"  regional / one matrix          {t_regional / t_decide:8.2f}   (goal <= 1.2)")
    print(f"  same, {paired}: {paired_regional:.2f}")
    print(f"  same, egoistic times 1 … 5 (the regional pass alone), {paired}: {paired_scaled:.2f}")
    if device == "cpu":
        print(
            f"  fused count pass: one matrix {1e3 * t_count_one:.1f} ms, RoI map, 5 matrices "
            f"{1e3 * t_count_regional:.1f} ms"
        )
        ratio = t_count_regional / t_count_one
        print(f"  regional / one matrix (fused count pass) {ratio:6.2f}   (goal <= 1.2)")
        print(f"  same, {paired}: {paired_count:.2f}")
    print(f"  decide_mixtures / decide       {t_mix / t_decide:8.2f}   (target <= 10)")
    print(f"  same, {paired}: {paired_mix:.2f}")
    if device == "cuda":
        gigabytes = probs.numel() * probs.element_size() / 1e9
        print(
            f"  effective bandwidth: decide {gigabytes / t_decide:.0f} GB/s, "
            f"p.sum() {gigabytes / t_sum:.0f} GB/s"
        )


def dense_matrix(n: int, seed: int) -> torch.Tensor:
    """A generic dense (N, N) matrix: off-diagonal costs uniform in [0.5, 10], zero diagonal."""
    gen = torch.Generator().manual_seed(seed)
    cost = 0.5 + 9.5 * torch.rand(n, n, generator=gen, dtype=torch.float64)
    return cost.fill_diagonal_(0.0)


def bench_counts(shape: tuple[int, int, int, int], repeats: int) -> None:
    """The fused pass against ``decide`` alone, and with a defer row against without (CPU)."""
    probs = probabilities(shape, "cpu")
    b, n, h, w = shape
    labels = torch.randint(0, n, (b, h, w), generator=torch.Generator().manual_seed(1))
    roi = (torch.arange(h) * 5 // h).view(h, 1).expand(h, w)  # five bands, ids 0..4
    prepared = prepare_counts(probs, labels, roi)
    nop, rounds = (lambda: None), 2 * repeats + 1
    print(f"cpu, {torch.get_num_threads()} threads, fused counts on {tuple(shape)} float32:")
    for name, cost in (("altruistic", VERTICES[1]), ("dense", dense_matrix(n, 0))):
        deferring = with_defer(cost, DEFER * cost.sum().item() / (n * n - n))
        fused = lambda c=cost: count_decisions(prepared, c)  # noqa: E731
        fused_defer = lambda c=deferring: count_decisions(prepared, c)  # noqa: E731
        alone = lambda c=cost: decide(probs, c)  # noqa: E731
        compiled = lambda c=cost: decide(probs, c, path="numba")  # noqa: E731
        t_fused, t_alone = best_time(fused, repeats, nop), best_time(alone, repeats, nop)
        t_defer = best_time(fused_defer, repeats, nop)
        print(
            f"  {name}: fused {1e3 * t_fused:.1f} ms, decide {1e3 * t_alone:.1f} ms, "
            f"fused with a defer row {1e3 * t_defer:.1f} ms"
        )
        paired, paired_numba = (paired_ratio(fused, f, rounds, nop) for f in (alone, compiled))
        print(
            f"    fused / decide          {t_fused / t_alone:6.2f}   (goal <= 1.5); "
            f"median of {rounds} rounds: {paired:.2f}"
        )
        print(f"    fused / decide (numba)  median: {paired_numba:.2f}")
        print(
            f"    defer / without         {t_defer / t_fused:6.2f}   (goal <= 1.2); "
            f"median: {paired_ratio(fused_defer, fused, rounds, nop):.2f}"
        )


def bench_candidates(count: int, share: float, ckpt: str | None) -> None:
    """Wall time of ``count`` random dense matrices scored on the demo's held-out images."""
    from costseg.data.toy import StreetScenes

    scenes = StreetScenes(split="val", length=100, size=(128, 256))
    held_out = range(50, 100)  # the second half of the toy val split
    images, labels = zip(*(scenes[i] for i in held_out), strict=True)
    labels = torch.stack(labels)
    source = "synthetic (smooth random logits)"
    if ckpt:
        from costseg.training.module import SegmentationModule

        model = SegmentationModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
        with torch.no_grad():
            probs = torch.cat([model(x[None]).softmax(1) for x in images])
        source = f"the model {ckpt}"
    else:
        probs = probabilities((len(labels), 19, 128, 256), "cpu")
    start = time.perf_counter()
    part = subsample(probs, labels, share=share) if share < 1 else None
    prepared = prepare_counts(*(part[:3] if part else (probs, labels)))
    prepare_s = time.perf_counter() - start
    count_decisions(prepared, dense_matrix(19, 0))  # the kernels loaded
    start = time.perf_counter()
    for k in range(count):
        count_decisions(prepared, dense_matrix(19, k + 1))
    wall = time.perf_counter() - start
    print(
        f"{count} random dense candidates on {len(labels)} images of 128 x 256, probabilities "
        f"of {source}, {share:.0%} of the labelled pixels ({prepared.q.shape[1]} in all): "
        f"{wall:.1f} s ({1e3 * wall / count:.1f} ms each; preparing them once: "
        f"{prepare_s:.2f} s)"
    )


@dataclass
class DecisionBenchOptions:
    """What ``bench_decision.py`` can be told (``--help``)."""

    repeats: int = option(5, "timed repeats of each path", type=whole_number(1))
    size: list[int] = option(
        [1024, 2048], "the probabilities' size", type=whole_number(1), nargs=2, metavar=("H", "W")
    )
    threads: int | None = option(help="CPU threads (default: torch's choice)", type=whole_number(1))
    devices: list[Literal["cpu", "cuda"]] = option(["cpu", "cuda"], "the devices timed")
    counts: bool = option(False, "the fused count pass (CPU)")
    candidates: int | None = option(
        help="time this many candidates (CPU)", type=whole_number(1), metavar="K"
    )
    pixel_share: float = option(
        1.0, "of the labelled pixels, for --candidates", type=share, flag="--share"
    )
    ckpt: str | None = option(help="the demo model's checkpoint, for --candidates", metavar="PATH")


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(DecisionBenchOptions, args, "bench_decision.py", __doc__.splitlines()[0])
    if args.threads:
        torch.set_num_threads(args.threads)
    shape = (1, 19, *args.size)
    if args.counts or args.candidates:
        if args.counts:
            bench_counts(shape, args.repeats)
            bench_counts((8, 19, 128, 256), args.repeats)
        if args.candidates:
            bench_candidates(args.candidates, args.pixel_share, args.ckpt)
        return
    for device in args.devices:
        if device == "cpu" or torch.cuda.is_available():
            bench(device, shape, args.repeats)


if __name__ == "__main__":
    main()
