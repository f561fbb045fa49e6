"""Figures drawn by the forkserver's workers equal those drawn in one process; failures, dead
and stalled workers end in one error; drawing cannot hang behind this process's threads."""

from __future__ import annotations

import os
import sys
import threading
import time

import numpy as np
import pytest
import torch
from interrupts import deadline, interrupt_when, start_job
from matplotlib.figure import Figure

from costseg import workers
from costseg.report.drawing import Drawing, job
from costseg.workers import Stalled


def draw(jobs, folder, processes):
    """Each job's drawn tags and shapes, on ``processes`` worker processes."""
    drawing = Drawing(folder, processes)
    for drawn_job in jobs:
        drawing.submit("prefix", drawn_job)
    return [figures for _, figures in drawing.finish()]


def redrawn(tags: list[str], seed: int):
    """A job like the report's: one figure redrawn with new data for each tag."""
    fig = Figure(figsize=(2, 1.5))
    ax = fig.subplots()
    line = ax.plot([0, 1], [0, 1])[0]
    for i, tag in enumerate(tags):
        line.set_ydata(np.random.default_rng(seed + i).random(2))
        ax.set_title(tag)
        yield tag, fig


def _jobs():
    return [job(redrawn, [f"b{b}_{i}" for i in range(b + 1)], 10 * b) for b in range(5)]


def test_two_workers_draw_what_one_draws(tmp_path):
    one = draw(_jobs(), tmp_path / "one", processes=1)
    two = draw(_jobs(), tmp_path / "two", processes=2)
    assert one == two
    assert [tag for figures in two for tag, _ in figures] == [
        f"b{b}_{i}" for b in range(5) for i in range(b + 1)
    ]
    assert all(shape == (150, 200, 3) for figures in two for _, shape in figures)
    names = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "two").iterdir())
    for name in names:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def failing(message: str):
    yield from redrawn(["fine"], 0)
    raise ValueError(message)


def test_an_error_in_a_worker_is_raised_with_its_traceback(tmp_path):
    with pytest.raises(RuntimeError, match=r"(?s)failed in a worker.*ValueError: boom"):
        draw([job(failing, "boom")], tmp_path, processes=2)


def test_a_failed_write_in_a_worker_is_the_os_error_naming_the_file(tmp_path):
    (tmp_path / "b.png").mkdir()  # the figure's file cannot be written
    with pytest.raises(OSError, match="Is a directory") as error:
        draw([job(redrawn, ["a", "b"], 0)], tmp_path, processes=1)
    assert str(tmp_path) in error.value.filename


def dies(code: int):
    os._exit(code)  # a worker killed, e.g. by the OOM killer
    yield


def test_a_dead_worker_is_one_error_not_a_hang(tmp_path):
    with pytest.raises(Stalled, match=r"ended with exit code 3 in prefix"):
        draw([job(dies, 3), job(redrawn, ["b"], 0)], tmp_path, processes=1)


def stalls(seconds: float):
    yield from redrawn(["before"], 0)
    time.sleep(seconds)  # alive and stuck, like a worker waiting on a lock nobody holds
    yield from redrawn(["after"], 0)


def test_a_stalled_worker_ends_the_wait_naming_where_it_stopped(tmp_path, monkeypatch):
    workers.start()  # the forkserver's own start is not the stall measured here
    monkeypatch.setattr(workers, "STALL_SECONDS", 10.0)  # a worker's start on a busy machine
    start = time.monotonic()
    with pytest.raises(Stalled, match=r"drew nothing for \d+ s \(pid \d+ after prefix/before\)"):
        draw([job(stalls, 600)], tmp_path, processes=1)
    assert time.monotonic() - start < 60


def test_a_job_that_carries_a_tensor_is_refused(tmp_path):
    import functools

    drawing = Drawing(tmp_path, processes=1)
    with pytest.raises(TypeError, match="carries a Tensor"):
        drawing.submit("prefix", functools.partial(redrawn, ["a"], torch.zeros(1)))
    drawing.cancel()
    assert job(redrawn, [torch.zeros(2, dtype=torch.float16)], 0).args[0][0].dtype == np.float16


def test_a_drawing_draws_while_the_caller_goes_on(tmp_path):
    drawing = Drawing(tmp_path, processes=1)
    drawing.submit("p", job(redrawn, ["early"], 0))
    deadline = time.monotonic() + 60
    while not (tmp_path / "early.png").exists():  # drawn by the worker, before finish()
        assert time.monotonic() < deadline, "the worker drew nothing"
        time.sleep(0.05)
    assert drawing.finish() == [("p", [("early", (150, 200, 3))])]


def busy_threads(stop: threading.Event) -> list[threading.Thread]:
    """Threads like an evaluation's: torch's intra-op pool kept busy above its grain size (a
    256 × 512 map) and costseg's thread pool, while the figures are started."""
    from costseg.workers import threads

    def torch_ops():
        x = torch.rand(4, 256, 512)
        while not stop.wait(0.005):
            x.half().float().mul_(1.0001)

    def pool_jobs():
        values = np.random.default_rng(0).random(1 << 14)
        while not stop.wait(0.005):
            threads().submit(np.sort, values).result()

    started = [threading.Thread(target=f, daemon=True) for f in (torch_ops, pool_jobs)]
    for thread in started:
        thread.start()
    return started


@pytest.mark.figures
def test_the_example_figures_never_hang_behind_busy_threads(tmp_path, monkeypatch):
    """10 times, each under a deadline: the evaluation's mask figures at 256 × 512 (float16
    uncertainty maps above torch's grain size) started while torch's pool and other threads run."""
    from costseg.report.early_figures import EarlyFigures
    from costseg.report.results import Example
    from costseg.rules.named import parse_rules, rules_group

    monkeypatch.setattr(workers, "STALL_SECONDS", 10.0)
    rng = torch.Generator().manual_seed(0)
    h, w = 256, 512
    example = Example(
        image=torch.randint(0, 256, (3, h, w), dtype=torch.uint8, generator=rng),
        label=torch.randint(0, 19, (h, w), generator=rng),
        preds=torch.randint(0, 19, (1, h, w), generator=rng),
        uncertainty={"entropy": torch.rand(h, w, generator=rng).half()},
    )
    group = rules_group(parse_rules(["robotistic"]))
    stop = threading.Event()
    running = busy_threads(stop)
    try:
        for attempt in range(10):
            out = tmp_path / str(attempt)
            with deadline(20, f"attempt {attempt + 1} of 10"):
                early = EarlyFigures(out, [group], None, num_examples=1)
                early.after_batch([example], [group])
                drawn = early.drawing.finish()
            assert [tag for _, figures in drawn for tag, _ in figures][-1] == "masks_0"
            assert (out / "figures" / "masks_0.png").stat().st_size > 0
    finally:
        stop.set()
        for thread in running:
            thread.join()


SLOW_FORKSERVER = """import os, time
from pathlib import Path

parent = os.getppid()
Path(__file__).with_name("started").touch()
deadline = time.monotonic() + 120
while os.getppid() == parent and time.monotonic() < deadline:
    time.sleep(0.05)
"""
"""A module the forkserver imports after its preloads, as a forkserver slowed down by a busy machine
would be: it says that it has started, then waits until its parent has ended."""

STARTS_WORKERS = """import os, sys, time
from pathlib import Path

os.environ["PYTHONPATH"] += os.pathsep + sys.argv[1]  # the forkserver's path
from costseg import workers

workers.CONTEXT.set_forkserver_preload([*workers.PRELOAD, "slow_forkserver"])
from costseg.cli import user_errors
from costseg.report.drawing import Drawing

with user_errors():
    Drawing(Path(sys.argv[1]) / "figures", 2)  # waits for the forkserver to fork a worker
    time.sleep(600)
"""
"""A job that starts the figure workers as an evaluation does, its Ctrl-C turned into one line."""


def test_ctrl_c_while_the_workers_start_leaves_one_line(tmp_path):
    """Ctrl-C while the forkserver has yet to fork the figure workers: the job prints its one
    line and ends; the worker forked after it ended (its queues gone) ends without a word."""
    (tmp_path / "slow_forkserver.py").write_text(SLOW_FORKSERVER)
    job = start_job([sys.executable, "-c", STARTS_WORKERS, str(tmp_path)])
    _, err = interrupt_when(job, (tmp_path / "started").exists)
    assert job.returncode == 130, err
    assert err.splitlines() == ["interrupted"], err
