"""The figures of ``--anomalies`` (docs/definitions.md §17), drawn by figure workers from NumPy
arrays: per example image the image, its anomaly mask and each anomaly score's map."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

MASK_COLOURS = ListedColormap(["0.15", "tab:red", "0.6"])  # known, unknown object, void


def anomaly_map_figures(
    examples: Sequence[tuple[np.ndarray, np.ndarray, Mapping[str, np.ndarray]]],
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """Per ``(image (H, W, 3) uint8, mask (H, W), {score: (H, W) map in [0, 1]})``: the image,
    the mask (red: unknown objects, grey: void) and the score maps, one row of panels, under a
    title with ``subject`` (the network and shift)."""
    for i, (image, mask, maps) in enumerate(examples):
        h, w = mask.shape
        columns = 2 + len(maps)
        rows = -(-columns // 4)
        fig = Figure(figsize=(16, rows * (16 / 4) * h / w + 1.2), layout="constrained")
        title = f"anomaly scores of example {i} with unknown objects added"
        fig.suptitle(f"{title}, {subject}" if subject else title, wrap=True)
        axes = np.atleast_1d(fig.subplots(rows, 4)).ravel()
        axes[0].imshow(image)
        axes[0].set_title("image")
        axes[1].imshow(np.where(mask == 255, 2, mask), cmap=MASK_COLOURS, vmin=0, vmax=2)
        axes[1].set_title("unknown objects")
        for ax, (name, values) in zip(axes[2:], maps.items(), strict=False):
            shown = ax.imshow(values.astype(np.float32), cmap="magma", vmin=0, vmax=1)
            ax.set_title(name.replace("cost_margin/", "cost margin: "))
        for ax in axes:
            ax.set_xticks([]), ax.set_yticks([])
        for ax in axes[columns:]:
            ax.set_visible(False)
        if maps:
            fig.colorbar(shown, ax=axes[:columns].tolist(), shrink=0.8, label="anomaly score")
        yield f"anomaly_maps_{i}", fig
