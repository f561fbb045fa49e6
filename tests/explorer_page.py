"""The data an ``explorer.html`` embeds, read back as the page's script reads it; a page that
opens explorer pages one after another and lists what each shows (one browser launch for many
states)."""

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


STATES_SCRIPT = """
const steps = %s, states = [];
let previous = "";
function run(i) {
  if (i === steps.length) {
    document.getElementById("states").textContent = JSON.stringify(states);
    return;
  }
  const step = steps[i], frame = document.createElement("iframe");
  const url = step.url === null ? previous : step.url;
  frame.onload = () => {
    const win = frame.contentWindow, doc = frame.contentDocument;
    if (step.slider !== null) {
      const slider = doc.getElementById("defer");
      slider.value = String(step.slider);
      slider.dispatchEvent(new win.Event("input"));
    }
    if (step.cls !== null) {
      const select = doc.getElementById("cls");
      select.value = step.cls;
      select.dispatchEvent(new win.Event("change"));
    }
    const pre = doc.getElementById("costseg-state");
    previous = url.split("#")[0] + win.location.hash;
    states.push({hash: win.location.hash, state: pre && JSON.parse(pre.textContent),
                 shown: doc.getElementById("defer-value").textContent,
                 metrics: doc.getElementById("metrics").textContent,
                 legend: doc.getElementById("legend").innerText,
                 choice: win.getComputedStyle(doc.getElementById("choice")).display,
                 visible: doc.body.innerText});
    frame.remove();
    run(i + 1);
  };
  frame.src = url;
  document.body.appendChild(frame);
}
run(0);
"""


def states_page(folder: Path, steps: list[tuple]) -> Path:
    """A page that opens explorer pages one after another in a frame and lists what each shows.

    Args:
        folder: where the page is written.
        steps: ``(page, fragment, slider[, cls])`` each: open ``page#fragment`` (``page``
            None: the previous step's page at the hash it ended with), then, unless ``slider``
            is None, move the defer slider to that position, and choose the class ``cls`` in
            the page's menu where given.

    Returns:
        The page; once its scripts ran (Chromium with ``--allow-file-access-from-files``, so a
        page may read its frames), its ``<pre id="states">`` holds a JSON list with, per step,
        ``{"hash", "state" (the costseg-state JSON), "shown" (the defer slider's text),
        "metrics" (the text of the metrics at the point), "legend" (the class legend's text),
        "choice" (the CSS display of the metric and class menus), "visible" (the text the
        page shows)}``.
    """
    plan = [
        {
            "url": None if page is None else f"{page.as_uri()}#{fragment}",
            "slider": slider,
            "cls": cls[0] if cls else None,
        }
        for page, fragment, slider, *cls in steps
    ]
    path = folder / "states.html"
    script = STATES_SCRIPT % json.dumps(plan)
    path.write_text(f'<!DOCTYPE html><pre id="states"></pre><script>{script}</script>')
    return path
