"""TPV-Former inference cost per preset and device: median ms per frame (6 images -> 200x200x16 labels) and peak memory.

    python benchmarks/inference.py                               # tiny on cpu (and cuda when present), 10 repeats
    python benchmarks/inference.py --presets paper --repeats 1 --warmup 0   # the full 1600x900 paper preset once
    python benchmarks/inference.py --presets tiny paper --devices cuda --dtypes fp32 fp16 --camera-size
        # each from six 1600x900 uint8 images on the device: the resize to the preset's input is timed too

Each (preset, device) runs in its own process so that peak memory (ru_maxrss on cpu, max_memory_allocated on cuda)
belongs to that configuration alone. Weights are random unless --checkpoint is given: the cost does not depend on them.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time


def child(
    preset_name: str,
    device_name: str,
    repeats: int,
    warmup: int,
    threads: int,
    checkpoint: str | None,
    dtype: str = "auto",
    camera_size: bool = False,
) -> dict:
    import contextlib

    import psutil
    import torch
    import torch.nn.functional as F

    from occvo_core.cameras import nuscenes_rig
    from occvo_core.models.tpvformer import TPVFormer, autocast, load_checkpoint, preset

    torch.set_num_threads(threads)
    device = torch.device(device_name)
    model = (
        load_checkpoint(checkpoint, device=device) if checkpoint else TPVFormer(preset(preset_name)).to(device).eval()
    )
    cfg = model.cfg
    w, h = cfg.input_size
    rig = nuscenes_rig(w, h)
    images = torch.rand(1, 6, 3, h, w, device=device)
    cameras = torch.randint(0, 256, (6, 3, 900, 1600), dtype=torch.uint8, device=device) if camera_size else None
    if dtype == "auto":  # the served default: bf16 autocast on cuda, fp32 on cpu
        cast = autocast(device)
    elif dtype == "fp32":
        cast = contextlib.nullcontext()
    else:
        cast = torch.autocast(device.type, dtype={"fp16": torch.float16, "bf16": torch.bfloat16}[dtype])
    k = torch.tensor(rig.intrinsics, dtype=torch.float32, device=device)[None]
    e = torch.tensor(rig.cam_to_ego, dtype=torch.float32, device=device)[None]
    rss_before = psutil.Process().memory_info().rss
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    with torch.no_grad():
        for i in range(warmup + repeats):
            t0 = time.perf_counter()
            with cast:
                if cameras is not None:  # as the predictor takes them: uint8 at the camera's size, resized here
                    x = cameras.float().div_(255.0)
                    if x.shape[-2:] != (h, w):
                        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
                    images = x[None]
                labels = model(images, k, e)[0].argmax(0)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            if i >= warmup:
                times.append((time.perf_counter() - t0) * 1e3)
    assert tuple(labels.shape) == tuple(cfg.grid_shape)
    out = {
        "preset": preset_name,
        "device": device_name,
        "threads": threads,
        "input": f"6x{w}x{h}" + (" from 6x1600x900" if camera_size else ""),
        "dtype": dtype,
        "params": model.num_parameters(),
        "repeats": repeats,
        "ms_median": statistics.median(times),
        "ms_min": min(times),
        "rss_before_mb": rss_before / 2**20,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if device.type == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", nargs="+", default=["tiny"])
    p.add_argument("--devices", nargs="+", help="default: cpu, plus cuda when present")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (the machine is shared)")
    p.add_argument("--checkpoint", help="time this checkpoint (its preset) instead of random weights")
    p.add_argument(
        "--dtypes",
        nargs="+",
        default=["auto"],
        choices=["auto", "fp32", "fp16", "bf16"],
        help="autocast dtype (auto: bf16 on cuda, fp32 on cpu, as served)",
    )
    p.add_argument("--camera-size", action="store_true", help="start from six 1600x900 uint8 images (resize timed)")
    p.add_argument("--json", help="also write the rows here")
    p.add_argument("--_child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args._child:
        row = child(
            *args._child, args.repeats, args.warmup, args.threads, args.checkpoint, args.dtypes[0], args.camera_size
        )
        print(json.dumps(row))
        return 0
    import torch

    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    rows = []
    for preset_name, device, dtype in ((p, d, t) for p in args.presets for d in devices for t in args.dtypes):
        cmd = [
            sys.executable,
            __file__,
            "--_child",
            preset_name,
            device,
            "--repeats",
            str(args.repeats),
            "--warmup",
            str(args.warmup),
            "--threads",
            str(args.threads),
            "--dtypes",
            dtype,
        ]
        cmd += (["--checkpoint", args.checkpoint] if args.checkpoint else []) + (
            ["--camera-size"] if args.camera_size else []
        )
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode:
            print(f"{preset_name}/{device}/{dtype} failed:\n{proc.stderr[-2000:]}", file=sys.stderr)
            continue
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        mem = (
            f"peak cuda {row['peak_cuda_mb']:.0f} MB"
            if "peak_cuda_mb" in row
            else f"peak RSS {row['peak_rss_mb']:.0f} MB (before forward {row['rss_before_mb']:.0f} MB)"
        )
        print(
            f"{preset_name:>6} {device:>5} {dtype:>4} x{row['threads']} thread(s)  input {row['input']:>12}  "
            f"params {row['params'] / 1e6:7.2f} M  "
            f"{row['ms_median']:9.1f} ms/frame median (min {row['ms_min']:.1f}, n={row['repeats']})  {mem}",
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
