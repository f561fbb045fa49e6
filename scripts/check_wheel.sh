#!/usr/bin/env bash
# The wheel works wherever it is installed: build it, install it into a fresh virtual environment
# and, from a folder outside the repository, run the three commands and load a packaged matrix.
#
#     bash scripts/check_wheel.sh          (after `make setup`; CI: .ci/run)
#
# The fresh environment gets costseg from the wheel only; the third-party packages (torch, ...)
# are those of .venv, made importable by a .pth file rather than downloaded again. A .pth line
# adds a folder without running the .pth files in it, so .venv's editable costseg stays out.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
python="$repo/.venv/bin/python"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

step() { printf '\n== %s (%d s so far)\n' "$*" "$SECONDS"; }

step "build the wheel"
# from a copy of the files git sees (tracked or not ignored): no stale build/ folder ships
mkdir "$work/tree"
git -C "$repo" ls-files -z --cached --others --exclude-standard |
    tar -C "$repo" --null --files-from=- --ignore-failed-read --warning=no-failed-read -cf - |
    tar -C "$work/tree" -xf -
"$python" -m pip wheel --quiet --no-deps --wheel-dir "$work/dist" "$work/tree"
wheel="$(ls "$work"/dist/costseg-*.whl)"
"$python" -c 'import sys, zipfile; names = zipfile.ZipFile(sys.argv[1]).namelist()
print(sys.argv[1].rsplit("/", 1)[-1] + ":", *sorted(n for n in names if n.endswith(".yaml")))' "$wheel"

step "install it into a fresh virtual environment"
"$python" -m venv --without-pip "$work/venv"
"$python" -m pip --python "$work/venv/bin/python" install --quiet --no-deps "$wheel"
site="$("$work/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
"$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' > "$site/venv_packages.pth"
bin="$work/venv/bin"
cd "$work"  # outside the repository: nothing of it on sys.path

step "costseg is the installed one"
"$bin/python" - "$work/venv" <<'EOF'
import sys
import costseg
assert costseg.__file__.startswith(sys.argv[1]), f"costseg imported from {costseg.__file__}"
print(costseg.__file__)
EOF

step 'load_cost("egoistic")'
"$bin/python" -c 'from costseg.costs import load_cost; c = load_cost("egoistic"); print(tuple(c.shape), "sum", c.sum().item())'

step "costseg-evaluate --help"
"$bin/costseg-evaluate" --help | head -3

step "costseg-train --print_config"
"$bin/costseg-train" --print_config | grep -E '^  (max_steps|    backbone)|class_path: costseg'

step "costseg-train: a tiny checkpoint (1 step)"
# The tests' tiny model (tests/conftest.py TINY_TRAIN), one step.
"$bin/costseg-train" --model.net.init_args.decoder_channels=16 --model.val_costs=[robotistic] \
    --data.init_args.size=[64,128] --data.init_args.batch_size=2 \
    --data.init_args.train_length=2 --data.init_args.val_length=1 \
    --data.init_args.test_length=1 --data.init_args.prior_images=2 \
    --data.init_args.num_workers=0 --trainer.precision=32-true --trainer.max_steps=1 \
    --trainer.val_check_interval=1 --trainer.enable_progress_bar=false \
    --trainer.enable_model_summary=false --trainer.logger.init_args.save_dir=runs 2>&1 | tail -1
ckpt="$(find runs -name last.ckpt | head -1)"
echo "$ckpt"

step "costseg-predict on one image"
"$bin/python" -c 'from PIL import Image; Image.new("RGB", (96, 64), (90, 120, 60)).save("photo.png")'
"$bin/costseg-predict" --input photo.png --ckpt_path "$ckpt" --cost egoistic \
    --output_dir predicted --no-progress
ls predicted
test -s predicted/counts.csv
echo "wheel check passed in $SECONDS s"
