"""Figures drawn on forked processes equal those drawn in one process, and failures surface."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from matplotlib.figure import Figure

from costseg.report.drawing import Drawing


def draw(batches, folder, processes):
    """Each batch's drawn tags and shapes, on ``processes`` processes."""
    drawn = Drawing([("prefix", batch) for batch in batches], folder, processes - 1).finish()
    return [figures for _, figures in drawn]


def _redrawn(tags: list[str], seed: int):
    """A batch like the report's: one figure redrawn with new data for each tag."""
    fig = Figure(figsize=(2, 1.5))
    ax = fig.subplots()
    line = ax.plot([0, 1], [0, 1])[0]
    for i, tag in enumerate(tags):
        line.set_ydata(np.random.default_rng(seed + i).random(2))
        ax.set_title(tag)
        yield tag, fig


def _batches():
    return [_redrawn([f"b{b}_{i}" for i in range(b + 1)], 10 * b) for b in range(5)]


def test_forked_drawing_equals_one_process(tmp_path):
    one = draw(_batches(), tmp_path / "one", processes=1)
    two = draw(_batches(), tmp_path / "two", processes=2)
    assert one == two
    assert [tag for batch in two for tag, _ in batch] == [
        f"b{b}_{i}" for b in range(5) for i in range(b + 1)
    ]
    assert all(shape == (150, 200, 3) for batch in two for _, shape in batch)
    names = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "two").iterdir())
    for name in names:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def _failing(message: str):
    yield from _redrawn(["fine"], 0)
    raise ValueError(message)


def test_an_error_in_any_process_is_raised(tmp_path):
    # Two failing batches: whichever the worker takes, its error reaches the caller; the one
    # the calling process takes raises as it is.
    with pytest.raises((RuntimeError, ValueError), match="boom"):
        draw([_failing("boom"), _failing("boom")], tmp_path, processes=2)


def _dies_in_a_worker(parent: int):
    if os.getpid() != parent:
        os._exit(3)  # a worker killed, e.g. by the OOM killer
    time.sleep(1)  # the worker claims the other batch meanwhile
    yield from _redrawn(["parent"], 0)


def test_a_dead_worker_is_an_error_not_a_hang(tmp_path):
    parent = os.getpid()
    with pytest.raises(RuntimeError, match=r"exit codes \[3\]"):
        draw([_dies_in_a_worker(parent), _dies_in_a_worker(parent)], tmp_path, processes=2)


def test_a_started_drawing_draws_while_the_caller_goes_on(tmp_path):
    drawing = Drawing([("p", _redrawn(["early"], 0))], tmp_path, workers=1)
    deadline = time.monotonic() + 60
    while not (tmp_path / "early.png").exists():  # drawn by the worker, before finish()
        assert time.monotonic() < deadline, "the worker drew nothing"
        time.sleep(0.05)
    assert drawing.finish() == [("p", [("early", (150, 200, 3))])]


def test_redrawing_only_the_changing_artists_paints_the_same_pixels():
    from costseg.costs import barycentric_grid
    from costseg.report.files import redraw_only, render
    from costseg.report.ternary import ternary_figures

    weights = barycentric_grid(0.1)
    rng = np.random.default_rng(0)
    panels = [(f"t{i}", rng.random(len(weights)), f"panel {i}", f"m{i % 2}") for i in range(3)]
    repainted = [render(fig) for _, fig in ternary_figures(weights, panels)]
    full = [render(redraw_only(fig, [])) for _, fig in ternary_figures(weights, panels)]
    assert len({image.tobytes() for image in full}) == 3  # the panels differ
    for a, b in zip(repainted, full, strict=True):
        np.testing.assert_array_equal(a, b)
