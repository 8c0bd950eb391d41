"""Inference worker: camera frames in (occvo/<stream>/camera), occupancy frames out (occvo/<stream>/occupancy).

Sources:
  replay  the frame's recorded occupancy (any occvo_core scene source, published by `occvo replay`): the paper's
          ground-truth occupancy row.
  model   a torch occupancy network on the six images (services.occupancy_model.OccupancyModel), on cuda or cpu.

Runs in its own process, so inference of frame t+1 overlaps registration of frame t in the registration worker.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import zenoh

from schemas import keys
from schemas.codec import encode
from schemas.models import CameraFrame, OccupancyFrameMsg, SparseOccupancy
from services.runtime import Worker, WorkerConfig, log_event, worker_main


class InferenceWorker(Worker):
    """Camera frames -> occupancy frames."""

    role = "inference"

    def __init__(self, config: WorkerConfig, model=None):
        super().__init__(config)
        self.model = model
        if config.source == "model" and model is None:
            import torch

            from services.occupancy_model import TorchOccupancyModel

            torch.set_num_threads(config.torch_threads)
            self.model = TorchOccupancyModel(device=config.device, weights=config.model_weights)
            log_event(self.log, "model loaded", model=self.model.name, device=str(self.model.device))

    def declare(self) -> None:
        self._declared.append(self.session.declare_subscriber(keys.camera("*"), self._on_camera))

    def _on_camera(self, sample: zenoh.Sample) -> None:
        self.enqueue(sample, CameraFrame, self._infer)

    def _infer(self, stream: str, item) -> None:
        msg, hop_ms, t_queued = item
        t0 = time.perf_counter()
        key = keys.camera(stream)
        if self.config.source == "replay":
            if msg.gt_occupancy is None:
                self.report_error(stream, "invalid_frame", f"seq {msg.seq}: the replay source needs the frame's recorded occupancy (gt_occupancy)", key, msg.seq)
                return
            occupancy, source = msg.gt_occupancy, "replay"
        else:
            if len(msg.images) != 6:
                self.report_error(stream, "invalid_frame", f"seq {msg.seq}: the model source needs 6 camera images, got {len(msg.images)}", key, msg.seq)
                return
            from services.occupancy_model import decode_image

            try:
                images = [decode_image(im) for im in msg.images]
            except ValueError as exc:
                self.report_error(stream, "invalid_frame", f"seq {msg.seq}: {exc}", key, msg.seq)
                return
            K = np.array([im.intrinsics for im in msg.images])
            T = np.array([im.extrinsics for im in msg.images])
            idx, labels = self.model.predict(images, K, T)
            dtype = np.uint8 if max(self.model.grid.shape) <= 256 else np.uint16
            occupancy = SparseOccupancy.model_validate({
                "grid": {"lower": self.model.grid.lower, "upper": self.model.grid.upper, "voxel_size": self.model.grid.voxel_size},
                "voxels": {"dtype": np.dtype(dtype).name, "shape": [len(idx), 3], "data": idx.astype(dtype).tobytes()},
                "labels": {"dtype": "uint8", "shape": [len(labels)], "data": labels.astype(np.uint8).tobytes()},
            })
            source = f"model:{self.model.name}"
        infer_ms = (time.perf_counter() - t0) * 1000.0
        queue_ms = (t0 - t_queued) * 1000.0
        out = OccupancyFrameMsg(stream=stream, seq=msg.seq, stamp=msg.stamp, source=source, occupancy=occupancy,
                                timings_ms={"camera_hop": hop_ms, "inference_queue": queue_ms, "inference": infer_ms},
                                sent_at=time.time())
        self.session.put(keys.occupancy(stream), encode(out, self.config.max_message_bytes),
                         congestion_control=zenoh.CongestionControl.BLOCK)
        self.stats.inc("frames_out")
        self.stats.observe("inference", infer_ms)
        self.stats.observe("camera_hop", hop_ms)
        self.stats.observe("queue", queue_ms)
        self.stats.observe("stage_total", (time.perf_counter() - t0) * 1000.0)


def _args(p) -> None:
    p.add_argument("--source", choices=["replay", "model"])
    p.add_argument("--device", choices=["auto", "cpu", "cuda"])
    p.add_argument("--model-weights")


if __name__ == "__main__":
    sys.exit(worker_main(InferenceWorker, extra_args=_args))
