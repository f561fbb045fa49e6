"""Run the README's commands as written (but train.py's), on a trained model.

    python scripts/run_doc_commands.py [--ckpt_path PATH] [--output_dir DIR] [--only TEXT]

Each command runs in its own process (evaluate.py and predict.py with ``--no-progress`` and an
``--output_dir`` of their own added). The files a reader brings are made first and put in place
of the README's stand-ins: ``photo.jpg`` and ``drive.mp4`` from procedural scenes, ``FILE.pth``
a VainF DeepLabV3+ with random weights, ``/data/cityscapes`` a 256 x 512 Cityscapes-layout tree,
``a.ckpt b.ckpt c.ckpt`` the model itself three times, ``model.onnx`` a file in the output
folder. train.py's synopsis and ``make`` lines are left out (``make demo`` trains). Prints one
line per command (exit status, wall time) and exits 1 if any failed.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.cli import parse_options, user_errors
from costseg.options import option

ROOT = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"^\s*(python3? (?:\S+/)?\S+\.py\b.*)$")
BACKSLASH = "\\"


@dataclass
class CommandsOptions:
    """What ``run_doc_commands.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="the model (default: the newest runs/**/last.ckpt)", metavar="PATH"
    )
    output_dir: Path = option(Path("runs/doc_commands"), "a new folder for the runs", type=Path)
    only: str | None = option(help="run only the commands that contain this text", metavar="TEXT")


def documented_commands(text: str) -> list[str]:
    """The ``python X.py ...`` lines of a page (continuation lines joined, comments dropped).

    >>> documented_commands("    python evaluate.py --sweep 0.1 \\\\\n        --explorer  # see")
    ['python evaluate.py --sweep 0.1 --explorer']
    """
    found, pending = [], None
    for line in text.splitlines():
        if pending is None:
            match = COMMAND.match(line)
            if not match:
                continue
            pending, line = "", match.group(1)
        body = line.split(" # ", 1)[0].strip()
        continued = body.endswith(BACKSLASH)
        pending = " ".join(p for p in (pending, body.removesuffix(BACKSLASH).strip()) if p)
        if not continued:
            found.append(pending)
            pending = None
    return found


def stand_ins(folder: Path, ckpt: str) -> dict[str, str]:
    """The README's stand-in paths → files made in ``folder``."""
    import torch
    from PIL import Image

    from costseg.data.toy import StreetScenes
    from costseg.networks import export_vainf_state
    from costseg.networks.vainf import vainf_deeplabv3plus

    folder.mkdir(parents=True, exist_ok=True)
    scenes = StreetScenes("test", 8, (256, 512), seed=7)
    frames = [scenes[i][0].permute(1, 2, 0).numpy() for i in range(len(scenes))]
    Image.fromarray(frames[0]).save(folder / "photo.jpg", quality=90)
    import av

    with av.open(str(folder / "drive.mp4"), "w") as video:
        stream = video.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 512, 256, "yuv420p"
        for frame in frames:
            video.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        video.mux(stream.encode())
    torch.manual_seed(0)
    net = vainf_deeplabv3plus(19, "resnet50", 16).eval()
    torch.save({"model_state": export_vainf_state(net)}, folder / "vainf_os16.pth")
    tree = folder / "cityscapes"
    subprocess.run([sys.executable, ROOT / "scripts" / "toy_as_cityscapes.py", str(tree),
                    "--train", "8", "--val", "4", "--size", "256", "512"], check=True)  # fmt: skip
    return {
        "photo.jpg": str(folder / "photo.jpg"),
        "drive.mp4": str(folder / "drive.mp4"),
        "FILE.pth": str(folder / "vainf_os16.pth"),
        "/data/cityscapes": str(tree),
        "a.ckpt": ckpt,
        "b.ckpt": ckpt,
        "c.ckpt": ckpt,
    }


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(CommandsOptions, args, "run_doc_commands.py", __doc__.splitlines()[0])
    from costseg.checkpoints import find_checkpoint

    ckpt = str(find_checkpoint(args.ckpt_path))
    if args.output_dir.exists():
        raise ValueError(f"{args.output_dir} exists: choose another --output_dir")
    readme = documented_commands((ROOT / "README.md").read_text())
    commands = [c for c in readme if c.split()[1] != "train.py" and (args.only or "") in c]
    replace = stand_ins(args.output_dir / "inputs", ckpt)
    replace["model.onnx"] = str(args.output_dir / "model.onnx")
    failed = 0
    for i, command in enumerate(commands):
        words = shlex.split(command)[1:]
        for stand_in, path in replace.items():
            words = [w.replace(stand_in, path) for w in words]
        if words[0] in ("evaluate.py", "predict.py"):
            if "--ckpt_path" not in words and "--network" not in words:
                words += ["--ckpt_path", ckpt]
            words += ["--no-progress", "--output_dir", str(args.output_dir / f"{i:02d}")]
        start = time.perf_counter()
        run = subprocess.run([sys.executable, *words], cwd=ROOT, capture_output=True, text=True)
        status = "ok" if run.returncode == 0 else f"exit {run.returncode}"
        print(f"{status:7} {time.perf_counter() - start:6.1f} s  {command}", flush=True)
        if run.returncode:
            failed += 1
            print("        " + (run.stderr.strip().splitlines() or ["(no message)"])[-1])
    print(f"{len(commands) - failed} of {len(commands)} README commands ran (outputs in "
          f"{args.output_dir})")  # fmt: skip
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    with user_errors():
        main()
