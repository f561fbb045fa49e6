"""The data an ``explorer.html`` embeds, read back as the page's script reads it."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import torch


def page_json(page: Path) -> dict:
    """The page's ``costseg-data`` JSON."""
    text = page.read_text()
    data = re.search(r'<script type="application/json" id="costseg-data">(.*?)</script>', text)
    assert data, f"{page} holds no costseg-data"
    return json.loads(data.group(1).replace("<\\/", "</"))


def embedded_probs(page: Path) -> dict[str, torch.Tensor]:
    """name → (N, H, W) float16 probabilities, decoded from the page's own data."""
    return {
        ex["name"]: torch.from_numpy(
            np.frombuffer(base64.b64decode(ex["probs"]), dtype="<f2")
            .reshape(-1, ex["height"], ex["width"])
            .copy()
        )
        for ex in page_json(page)["examples"]
    }
