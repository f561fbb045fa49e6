"""Speed of the decision layer, the value-space sweep and training, as side-by-side ratios.

    python scripts/bench.py [--skip-sweep] [--skip-train]

Every ratio compares two timings taken in the same run on the same tensors (best of several
repeats), so a loaded machine shifts both alike. Sections:

1. decision layer on (1, 19, 512, 1024) fp32 probabilities on the CPU: single-rule ``decide`` ÷
   ``torch.argmax(p, 1)`` and ÷ one read pass ``p.sum()``; ``decide_mixtures`` over the 66-point
   grid ÷ single-rule ``decide`` (and the naive loop over 66 matrices, for reference);
   on a GPU, if there is one, the same at (1, 19, 1024, 2048) with effective GB/s;
2. a 231-point sweep (step 0.05) ÷ a single-rule evaluation over the same toy validation set,
   network included, with the newest checkpoint under runs/ (or an untrained model);
3. training throughput (images/s) of the default config ``configs/toy.yaml``; on a GPU also of
   ``configs/cityscapes.yaml``'s network (crop 768, batch 8, bf16 autocast, channels-last).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import torch
import yaml

from costseg.costs import barycentric_grid, load_cost, mix_costs
from costseg.decision import decide, decide_mixtures

ROOT = Path(__file__).resolve().parents[1]
VERTICES = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])


def best_time(fn: Callable[[], object], repeats: int = 5, sync: Callable = lambda: None) -> float:
    """Best wall time of ``repeats`` calls, after one warm-up call."""
    fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return min(times)


def probabilities(shape: tuple[int, ...], device: str) -> torch.Tensor:
    """Softmax of smooth random logits: confident almost everywhere, unsure near borders."""
    gen = torch.Generator().manual_seed(0)
    b, n, h, w = shape
    coarse = torch.randn(b, n, h // 16, w // 16, generator=gen) * 6
    logits = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear")
    return logits.softmax(1).to(device)


def bench_decision(device: str, shape: tuple[int, ...]) -> None:
    probs = probabilities(shape, device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    grid = barycentric_grid(0.1)
    t_argmax = best_time(lambda: probs.argmax(1), sync=sync)
    t_sum = best_time(lambda: probs.sum(), sync=sync)
    t_decide = best_time(lambda: decide(probs, VERTICES[2]), sync=sync)
    t_mix = best_time(lambda: decide_mixtures(probs, VERTICES, grid), repeats=2, sync=sync)
    mixed = mix_costs(VERTICES, grid)
    t_loop = best_time(lambda: [decide(probs, c) for c in mixed], repeats=1, sync=sync)
    print(f"decision layer, {device}, probabilities {tuple(shape)} fp32:")
    print(f"  argmax {1e3 * t_argmax:8.1f} ms   p.sum() {1e3 * t_sum:8.1f} ms")
    print(f"  decide (egoistic)              {1e3 * t_decide:8.1f} ms")
    print(f"  decide / argmax                {t_decide / t_argmax:8.2f}   (target <= 1.0)")
    print(f"  decide / p.sum()               {t_decide / t_sum:8.2f}")
    print(f"  decide_mixtures, 66 points     {1e3 * t_mix:8.1f} ms")
    print(f"  decide_mixtures / decide       {t_mix / t_decide:8.2f}   (target <= 10)")
    print(f"  loop of 66 decide / decide     {t_loop / t_decide:8.2f}   (the naive way)")
    if device == "cuda":
        gigabytes = probs.numel() * probs.element_size() / 1e9
        print(
            f"  effective bandwidth: decide {gigabytes / t_decide:.0f} GB/s, "
            f"argmax {gigabytes / t_argmax:.0f} GB/s, p.sum() {gigabytes / t_sum:.0f} GB/s"
        )


def bench_sweep() -> None:
    from costseg.checkpoints import find_checkpoint
    from costseg.eval_job import EvalOptions, load_model, make_loader
    from costseg.evaluation import RuleGroup, evaluate
    from costseg.rules import apply_rules, parse_rules
    from costseg.sweep import sweep_group

    try:
        module, _ = load_model(EvalOptions(ckpt_path=str(find_checkpoint(None))))
    except FileNotFoundError:
        print("sweep: no checkpoint under runs/ (run `make demo` first); skipped")
        return
    loader = make_loader(module, EvalOptions())
    rules = parse_rules(["robotistic"])
    single = RuleGroup(["robotistic"], lambda p, pri: apply_rules(p, rules, pri))
    sweep = sweep_group(VERTICES, barycentric_grid(0.05))
    classes = [11, 2]
    t_single = best_time(lambda: evaluate(module, loader, [single], classes, progress=False), 1)
    t_sweep = best_time(lambda: evaluate(module, loader, [sweep], classes, progress=False), 1)
    images = len(loader.dataset)
    print(f"value-space sweep on the toy validation set ({images} images, network included):")
    print(f"  single-rule evaluation {t_single:7.1f} s   231-point sweep {t_sweep:7.1f} s")
    print(f"  sweep / single rule            {t_sweep / t_single:8.2f}   (target <= 5; ~231 naive)")


def bench_training(steps: int = 5) -> None:
    from costseg.data.datamodule import StreetScenesDataModule
    from costseg.module import SegmentationModule

    config = yaml.safe_load((ROOT / "configs" / "toy.yaml").read_text())
    module = SegmentationModule(**config["model"])
    data = StreetScenesDataModule(**{**config["data"]["init_args"], "num_workers": 0})
    images, labels = next(iter(_batches(data)))
    optimizer = torch.optim.AdamW(module.parameters(), lr=1e-3)
    precision = str(config["trainer"]["precision"])
    step = _training_step(module.train(), images, labels, optimizer, precision.startswith("bf16"))
    t_step = best_time(step, repeats=steps)
    size = tuple(images.shape[-2:])
    print(
        f"training, default config on the CPU ({config['model']['backbone']}, {size}, batch "
        f"{len(images)}, {precision}, {torch.get_num_threads()} threads): "
        f"{len(images) / t_step:.1f} images/s"
    )


def bench_training_cuda(steps: int = 10) -> None:
    from costseg.module import SegmentationModule

    config = yaml.safe_load((ROOT / "configs" / "cityscapes.yaml").read_text())
    model, data = config["model"], config["data"]["init_args"]
    torch.backends.cudnn.benchmark = True
    module = SegmentationModule(**{**model, "backbone_weights": None}).cuda().train()
    batch, crop = data["batch_size"], data["crop_size"]
    images = torch.randint(0, 256, (batch, 3, crop, crop), dtype=torch.uint8, device="cuda")
    labels = torch.randint(0, model["num_classes"], (batch, crop, crop), device="cuda")
    optimizer = torch.optim.SGD(
        module.parameters(), model["lr"], model["momentum"], weight_decay=model["weight_decay"]
    )
    step = _training_step(module, images, labels, optimizer, bf16=True)
    t_step = best_time(lambda: [step() for _ in range(steps)], 3, torch.cuda.synchronize) / steps
    print(
        f"training, Cityscapes config on {torch.cuda.get_device_name()} ({model['backbone']} "
        f"OS{model['output_stride']}, crop {crop}, batch {batch}, bf16): "
        f"{batch / t_step:.1f} images/s, peak memory "
        f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB"
    )


def _training_step(module, images, labels, optimizer, bf16: bool) -> Callable[[], None]:
    """One forward (bf16 autocast or not), cross-entropy, backward and update, as a closure."""

    def step() -> None:
        with torch.autocast(images.device.type, torch.bfloat16, enabled=bf16):
            logits = module(images)
        loss = torch.nn.functional.cross_entropy(logits.float(), labels, ignore_index=255)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return step


def _batches(data):
    data.setup("fit")
    return data.train_dataloader()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-sweep", action="store_true")
    parser.add_argument("--skip-train", action="store_true")
    args = parser.parse_args()
    bench_decision("cpu", (1, 19, 512, 1024))
    if torch.cuda.is_available():
        bench_decision("cuda", (1, 19, 1024, 2048))
    if not args.skip_sweep:
        bench_sweep()
    if not args.skip_train:
        bench_training()
        if torch.cuda.is_available():
            bench_training_cuda()


if __name__ == "__main__":
    main()
