"""Speed of the decision layer at Cityscapes scale, as ratios measured side by side in one run.

    python scripts/bench_decision.py [--repeats 5] [--size 1024 2048] [--threads N]

On (1, 19, H, W) float32 probabilities (softmax of smooth random logits, the recipe of
``scripts/bench.py``), on the CPU and, when there is one, on the GPU: one read pass ``p.sum()``,
``torch.argmax(p, 1)``, single-rule ``decide`` (egoistic, and egoistic with a defer row of
:data:`DEFER` times its mean off-diagonal cost, docs/definitions.md §14) and ``decide_mixtures``
over the 66-point barycentric grid (robotistic / altruistic / egoistic vertices, unscaled), on the
CPU also without numba's kernels. Each timing is the best of several repeats after a warm-up; every
ratio compares timings of the same run. The target ratios are also given as the median over
rounds that time both sides back to back (a machine whose speed drifts moves both alike).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from costseg.costs import barycentric_grid, load_cost, with_defer
from costseg.decision import DEFERRED, decide, decide_mixtures

VERTICES = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
DEFER = 0.5  # × the egoistic matrix's mean off-diagonal cost: about 5 % of pixels deferred


def egoistic_with_defer() -> torch.Tensor:
    """The egoistic matrix with a defer row of ``DEFER`` times its mean off-diagonal cost."""
    cost, n = VERTICES[2], VERTICES.shape[-1]
    return with_defer(cost, DEFER * cost.sum().item() / (n * n - n))


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


def bench(device: str, shape: tuple[int, int, int, int], repeats: int) -> None:
    """Print the timings and ratios on one device."""
    probs = probabilities(shape, device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    grid = barycentric_grid(0.1)
    run_sum, run_decide = (lambda: probs.sum()), (lambda: decide(probs, VERTICES[2]))
    deferring = egoistic_with_defer().to(device)
    run_defer = lambda: decide(probs, deferring)  # noqa: E731
    run_mix = lambda: decide_mixtures(probs, VERTICES, grid)  # noqa: E731
    t_sum = best_time(run_sum, repeats, sync)
    t_argmax = best_time(lambda: probs.argmax(1), repeats, sync)
    t_decide = best_time(run_decide, repeats, sync)
    t_defer = best_time(run_defer, repeats, sync)
    deferred = (run_defer() == DEFERRED).float().mean().item()
    t_mix = best_time(run_mix, max(3, repeats // 2), sync)
    rounds = 2 * repeats + 1
    paired_decide = paired_ratio(run_decide, run_sum, rounds, sync)
    paired_mix = paired_ratio(run_mix, run_decide, rounds, sync)
    paired_defer = paired_ratio(run_defer, run_decide, rounds, sync)
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
    print(f"  decide_mixtures / decide       {t_mix / t_decide:8.2f}   (target <= 10)")
    print(f"  same, {paired}: {paired_mix:.2f}")
    if device == "cuda":
        gigabytes = probs.numel() * probs.element_size() / 1e9
        print(
            f"  effective bandwidth: decide {gigabytes / t_decide:.0f} GB/s, "
            f"p.sum() {gigabytes / t_sum:.0f} GB/s"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--size", type=int, nargs=2, default=(1024, 2048), metavar=("H", "W"))
    parser.add_argument("--threads", type=int, help="CPU threads (default: torch's choice)")
    parser.add_argument("--devices", nargs="+", default=["cpu", "cuda"], choices=["cpu", "cuda"])
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    shape = (1, 19, *args.size)
    for device in args.devices:
        if device == "cpu" or torch.cuda.is_available():
            bench(device, shape, args.repeats)


if __name__ == "__main__":
    main()
