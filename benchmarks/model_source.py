"""The inference worker's model source vs OccupancyPredictor called directly, on the same rendered camera frames.

    python benchmarks/model_source.py --checkpoint /tmp/occvo-tiny/checkpoint.pt [--frames 20] [--repeats 2]

A worker process (`python -m occvo_services.inference_worker --source model --checkpoint ...`, router in this process,
loopback) and the predictor in this process (torch threads 1 in both) take turns on each frame, so both see the same
machine load: the predictor's `predict` is timed here, then the frame goes to the worker (the next only when the
occupancy of the last is back). The worker's stats queryable gives the p50 of its `model` stage (the same `predict`
call), `decode_images` and `inference` (decode + model + wire message). Prints medians over repeats, the
worker/direct ratio, and the client's round trip per frame.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import torch
import zenoh

REPO = Path(__file__).resolve().parents[1]

from occvo_core.cameras import CAMERA_NAMES  # noqa: E402
from occvo_core.models.image_source import ImageOccupancySource  # noqa: E402
from occvo_core.models.tpvformer import OccupancyPredictor  # noqa: E402
from occvo_core.sim import SyntheticScene  # noqa: E402
from occvo_schemas import keys  # noqa: E402
from occvo_schemas.codec import decode, encode  # noqa: E402
from occvo_schemas.models import CameraFrame, ErrorEvent, OccupancyFrameMsg, WorkerHealth  # noqa: E402
from occvo_services.local import wait_alive  # noqa: E402
from occvo_services.occupancy_model import camera_inputs, encode_image  # noqa: E402
from occvo_services.sessions import free_port, open_router, open_session  # noqa: E402


def paired(predictor, checkpoint, frames, threads) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    cmd = [
        sys.executable,
        "-m",
        "occvo_services.inference_worker",
        "--connect",
        ep,
        "--source",
        "model",
        "--checkpoint",
        str(checkpoint),
        "--device",
        "cpu",
        "--torch-threads",
        str(threads),
        "--worker-id",
        "inference-bench",
        "--log-level",
        "WARNING",
    ]
    proc = subprocess.Popen(cmd, cwd=REPO)
    session = open_session(ep)
    try:
        wait_alive(session, ["inference"], 180)
        done, cv = {}, threading.Condition()

        def on_out(sample):
            msg = decode(sample.payload.to_bytes(), (OccupancyFrameMsg, ErrorEvent))
            with cv:
                done[msg.seq] = msg
                cv.notify_all()

        subs = [
            session.declare_subscriber(keys.occupancy("bench"), on_out),
            session.declare_subscriber(keys.errors("bench"), on_out),
        ]
        pub = session.declare_publisher(keys.camera("bench"), congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(1.0)  # our subscribers reach the router
        rtt, direct = [], []
        for seq, imgs in enumerate(frames):
            images, k, e = camera_inputs(imgs)  # what the worker hands to predict
            t = time.perf_counter()
            predictor.predict(images, k, e)
            direct.append((time.perf_counter() - t) * 1000.0)
            t = time.perf_counter()
            pub.put(encode(CameraFrame(stream="bench", seq=seq, stamp=0.5 * seq, images=imgs, sent_at=time.time())))
            with cv:
                if not cv.wait_for(lambda s=seq: s in done, 120):
                    raise TimeoutError(f"no occupancy for seq {seq}")
            if not isinstance(done[seq], OccupancyFrameMsg):
                raise RuntimeError(done[seq].message)
            rtt.append((time.perf_counter() - t) * 1000.0)
        health = decode(
            next(iter(session.get(keys.stats("inference-bench"), timeout=10))).ok.payload.to_bytes(), WorkerHealth
        )
        for s in subs:
            s.undeclare()
    finally:
        session.close()
        proc.terminate()
        proc.wait(60)
        router.close()
    st = health.stages
    return {
        "direct_predict_median": statistics.median(direct[2:]),
        "model_p50": st["model"].p50_ms,
        "decode_images_p50": st["decode_images"].p50_ms,
        "inference_p50": st["inference"].p50_ms,
        "round_trip_median": statistics.median(rtt[2:]),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--encoding", default="jpeg", choices=["jpeg", "png", "raw_rgb8"])
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    predictor = OccupancyPredictor(args.checkpoint, device="cpu")
    source = ImageOccupancySource(SyntheticScene(seed=0, frames=args.frames), predictor)
    frames = []
    for i in range(args.frames):
        images, k, e = source.camera_frame(i)
        frames.append([encode_image(images[c], CAMERA_NAMES[c], k[c], e[c], args.encoding) for c in range(6)])
    runs = []
    for r in range(args.repeats):
        runs.append(paired(predictor, args.checkpoint, frames, args.threads))
        print(json.dumps({"repeat": r, **{k: round(v, 1) for k, v in runs[-1].items()}}), flush=True)
    med = {k: statistics.median(run[k] for run in runs) for k in runs[0]}
    med["worker_model_over_direct"] = med["model_p50"] / med["direct_predict_median"]
    print(
        json.dumps(
            {
                "checkpoint": args.checkpoint,
                "frames": args.frames,
                "repeats": args.repeats,
                "encoding": args.encoding,
                "torch_threads": args.threads,
                **{k: round(v, 3 if "over" in k else 1) for k, v in med.items()},
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
