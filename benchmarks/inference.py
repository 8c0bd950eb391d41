"""TPV-Former inference cost per preset and device: median ms per frame (6 images -> 200x200x16 labels) and peak memory.

    python benchmarks/inference.py                               # tiny on cpu (and cuda when present), 10 repeats
    python benchmarks/inference.py --presets paper --repeats 1 --warmup 0   # the full 1600x900 paper preset once

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


def child(preset_name: str, device_name: str, repeats: int, warmup: int, threads: int, checkpoint: str | None) -> dict:
    import psutil
    import torch

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
    k = torch.tensor(rig.intrinsics, dtype=torch.float32, device=device)[None]
    e = torch.tensor(rig.cam_to_ego, dtype=torch.float32, device=device)[None]
    rss_before = psutil.Process().memory_info().rss
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    with torch.no_grad():
        for i in range(warmup + repeats):
            t0 = time.perf_counter()
            with autocast(device):
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
        "input": f"6x{w}x{h}",
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
    p.add_argument("--json", help="also write the rows here")
    p.add_argument("--_child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args._child:
        print(json.dumps(child(*args._child, args.repeats, args.warmup, args.threads, args.checkpoint)))
        return 0
    import torch

    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    rows = []
    for preset_name in args.presets:
        for device in devices:
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
            ] + (["--checkpoint", args.checkpoint] if args.checkpoint else [])
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode:
                print(f"{preset_name}/{device} failed:\n{proc.stderr[-2000:]}", file=sys.stderr)
                continue
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            rows.append(row)
            mem = (
                f"peak cuda {row['peak_cuda_mb']:.0f} MB"
                if "peak_cuda_mb" in row
                else f"peak RSS {row['peak_rss_mb']:.0f} MB (before forward {row['rss_before_mb']:.0f} MB)"
            )
            print(
                f"{preset_name:>6} {device:>5} x{row['threads']} thread(s)  input {row['input']:>12}  params {row['params'] / 1e6:7.2f} M  "
                f"{row['ms_median']:9.1f} ms/frame median (min {row['ms_min']:.1f}, n={row['repeats']})  {mem}",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
