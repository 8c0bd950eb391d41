#!/usr/bin/env bash
# The camera model on one CUDA GPU, in under 6 minutes (docs/model.md, "On a GPU"):
#   1. inference ms/frame of the tiny and paper presets, fp32 and fp16 autocast, batch 1, from six 1600x900 images;
#   2. the `small` preset trained for --minutes on a prepared cache of rendered and real frames (bf16 autocast).
#
# Where ../shared is (no GPU needed), once:
#   benchmarks/gpu_check.sh --prepare            # writes benchmarks/gpu-cache/ (git-ignored, about 35 MB)
#   benchmarks/gpu_check.sh --wheels             # writes .whl/: the packages the GPU image lacks (pydantic, json5, zenoh)
# On the GPU machine (the device tool: carry benchmarks/gpu-cache and .whl):
#   benchmarks/gpu_check.sh [--minutes 3] [--out DIR]
# --device cpu runs the same steps on the CPU (a smoke test of the plumbing: --presets tiny --minutes 0.2).
set -euo pipefail
cd "$(dirname "$0")/.."

CACHE=benchmarks/gpu-cache
DRIVE=../shared/data/nuscenes-mini
MINUTES=3
OUT=${OUT:-/tmp/gpu-check}
DEVICE=cuda
PRESETS="tiny paper"
REPEATS=20
MODE=check
PYTHON=${PYTHON:-python3}

usage() { sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; }
while [ $# -gt 0 ]; do
  case "$1" in
    --prepare) MODE=prepare ;;
    --wheels) MODE=wheels ;;
    --cache) CACHE=$2; shift ;;
    --drive) DRIVE=$2; shift ;;
    --minutes) MINUTES=$2; shift ;;
    --out) OUT=$2; shift ;;
    --device) DEVICE=$2; shift ;;
    --presets) PRESETS=$2; shift ;;
    --repeats) REPEATS=$2; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "gpu_check.sh: unknown argument $1 (--help lists them)" >&2; exit 2 ;;
  esac
  shift
done

# The cache: seeds 0-1's frames 0, 5, 10, 15 rendered at small's input size, and keyframes 0-11 of scene-0916 with
# labels from sweeps 0-11 (the honest split's training side), stored at the input size.
SEEDS="0 1"
if [ "$MODE" = prepare ]; then
  [ -d "$DRIVE/v1.0-mini" ] || { echo "gpu_check.sh: no nuScenes drive at $DRIVE (--drive DIR)" >&2; exit 2; }
  mkdir -p "$CACHE"
  "$PYTHON" -m occvo_cli.cli make-occupancy --input "$DRIVE" --scene scene-0916 --keyframes 0-11 \
    --sweeps-from 0-11 --out "$CACHE/labels" --quiet >/dev/null
  "$PYTHON" - "$CACHE" "$DRIVE" "$SEEDS" <<'EOF'
import sys
from pathlib import Path

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.models.drive_training import DriveFrames
from occvo_core.models.tpvformer import preset
from occvo_core.models.training_data import prerender

cache, drive, seeds = Path(sys.argv[1]), sys.argv[2], [int(s) for s in sys.argv[3].split()]
size = preset("small").input_size
prerender(seeds, 20, 5, size, cache / "synthetic", jobs=1, progress=False)
frames = DriveFrames.from_drive(NuScenesDrive(drive, "scene-0916"), cache / "labels", range(12), size, stored=size)
frames.save(cache / "drive.npz")
EOF
  rm -rf "$CACHE/labels"
  du -sh "$CACHE"
  exit 0
fi
if [ "$MODE" = wheels ]; then
  exclude=$(git rev-parse --git-path info/exclude)  # a worktree's too
  grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"
  "$PYTHON" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    pydantic==2.13.4 pydantic-core==2.46.4 annotated-types==0.7.0 typing-inspection==0.4.2 json5==0.17.3 \
    eclipse-zenoh==1.10.2
  ls .whl
  exit 0
fi

[ -f "$CACHE/drive.npz" ] || { echo "gpu_check.sh: no cache at $CACHE: run benchmarks/gpu_check.sh --prepare" >&2; exit 2; }
if [ -d .whl ]; then
  "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
fi
export PYTHONPATH=$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1
mkdir -p "$OUT"
if [ "$DEVICE" = cuda ]; then
  "$PYTHON" -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; print(torch.cuda.get_device_name())"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
fi
start=$(date +%s)
# shellcheck disable=SC2086
"$PYTHON" benchmarks/inference.py --presets $PRESETS --devices "$DEVICE" --dtypes fp32 fp16 --camera-size \
  --repeats "$REPEATS" --warmup 3 --json "$OUT/inference.json"
echo "inference: $(( $(date +%s) - start )) s"
# shellcheck disable=SC2046
"$PYTHON" -m occvo_cli.cli train-occ --preset small --device "$DEVICE" --minutes "$MINUTES" --out "$OUT/small" \
  --seeds $SEEDS --frames 20 --stride 5 --cache "$CACHE/synthetic" --drive-cache "$CACHE/drive.npz" \
  --threads 4 --quiet --json | tee "$OUT/train.json"
echo "total: $(( $(date +%s) - start )) s"
