"""Inference worker: camera frames in (occvo/<stream>/camera), occupancy frames out (occvo/<stream>/occupancy).

Sources:
  replay  the frame's recorded occupancy (any occvo_core scene source, published by `occvo replay`): the paper's
          ground-truth occupancy row.
  model   a torch occupancy network on the six images: the trained TPV-Former of `checkpoint` (occvo train-occ), on
          cuda with bf16 autocast when present, else cpu (occvo_services.occupancy_model.load_occupancy_model).

Runs in its own process, so inference of frame t+1 overlaps registration of frame t in the registration worker.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np
import zenoh

from occvo_core.errors import ConfigError
from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import SHAPES_ONLY, CameraFrame, OccupancyFrameMsg, SparseOccupancy
from occvo_services.flow import SeqRanges
from occvo_services.runtime import Worker, WorkerConfig, log_event
from occvo_services.wire import blocking
from occvo_services.worker_cli import worker_main


class InferenceWorker(Worker):
    """Camera frames -> occupancy frames."""

    role = "inference"

    def __init__(self, config: WorkerConfig, model=None):
        super().__init__(config)
        # the replay source publishes a frame's recorded occupancy as its own output: checked voxel by voxel here, so
        # a label or voxel no reader accepts is this frame's error, never a message that fails downstream (0.2 ms a
        # frame); the model source does not read it: its arrays' shapes only
        self.input_context = {SHAPES_ONLY: True} if config.source == "model" else None
        self.model = model
        self._model_lock = threading.Lock()  # one network, one device: streams take turns
        self._forwarded: dict[str, SeqRanges] = {}  # per stream, the seqs forwarded (resends pass: check_seq)
        if config.source == "model" and model is None:
            import torch

            from occvo_services.occupancy_model import load_occupancy_model

            torch.set_num_threads(config.torch_threads)
            self.model = load_occupancy_model(
                config.checkpoint,
                config.model_weights,
                config.device,
                config.min_confidence,
                config.min_ground_confidence,
                config.camera_mask,
            )
            log_event(
                self.log,
                "model loaded",
                model=self.model.name,
                device=str(self.model.device),
                checkpoint=config.checkpoint,
                torch_threads=config.torch_threads,
                min_confidence=config.min_confidence,
                min_ground_confidence=config.min_ground_confidence,
                camera_mask=config.camera_mask,
            )

    def declare(self) -> None:
        self._declared.append(self.session.declare_subscriber(keys.camera("*"), self._on_camera))

    def check_seq(self, stream: str, seq: int, key: str) -> bool:
        """A step back to a frame forwarded before is a resend (its pose was lost, e.g. the registration worker
        restarted, or a full queue there turned it away while the client sent hundreds more): forward it; the
        registration worker answers it from its stored trajectory or registers it in its turn."""
        forwarded = self._forwarded.setdefault(stream, SeqRanges())
        expected = self.trackers[stream].expected
        if expected is not None and seq < expected and seq in forwarded:
            return True
        ok = super().check_seq(stream, seq, key)
        if ok:
            forwarded.add(seq)
        return ok

    def retire_stream(self, stream: str) -> None:
        """An idle stream's sequence state goes too (a flood of stream ids would keep one of each otherwise); its
        next frame starts the check afresh, and the registration worker judges it against the stored trajectory."""
        self.trackers.pop(stream, None)
        self._forwarded.pop(stream, None)

    def _on_camera(self, sample: zenoh.Sample) -> None:
        self.enqueue(sample, CameraFrame, self._infer)

    def _infer(self, stream: str, item) -> None:
        """One camera frame: its occupancy (recorded, or the network's), published for registration."""
        msg, hop_ms, t_queued, decode_ms, source_info = item[:5]
        t0 = time.perf_counter()
        got = self._replayed(stream, msg) if self.config.source == "replay" else self._predicted(stream, msg, t0)
        if got is None:
            return
        occupancy, source = got
        infer_ms = (time.perf_counter() - t0) * 1000.0
        queue_ms = (t0 - t_queued) * 1000.0
        out = OccupancyFrameMsg.model_construct(  # its parts validated: the camera frame's, the network's, the timings
            stream=stream,
            seq=msg.seq,
            stamp=msg.stamp,
            source=source,
            occupancy=occupancy,
            timings_ms={
                "camera_hop": hop_ms,
                "camera_decode": decode_ms,
                "inference_queue": queue_ms,
                "inference": infer_ms,
            },
            sent_at=time.time(),
        )
        t_encode = time.perf_counter()
        data = encode(out, self.config.max_message_bytes)
        self.stats.observe("encode", (time.perf_counter() - t_encode) * 1000.0)
        # the client's source info goes on: the registration worker knows the stream's client by it (limits.py)
        self.session.put(keys.occupancy(stream), data, **blocking("occupancy_frame"), source_info=source_info)
        self.stats.inc("frames_out")
        self.stats.observe("inference", infer_ms)
        self.stats.observe("camera_hop", hop_ms)
        self.stats.observe("queue", queue_ms)
        self.stats.observe("stage_total", (time.perf_counter() - t0) * 1000.0)

    def _replayed(self, stream: str, msg) -> tuple[SparseOccupancy, str] | None:
        if msg.gt_occupancy is None:
            self.report_error(
                stream,
                "invalid_frame",
                f"seq {msg.seq}: the replay source needs the frame's recorded occupancy (gt_occupancy)",
                keys.camera(stream),
                msg.seq,
            )
            return None
        return msg.gt_occupancy, "replay"

    def _predicted(self, stream: str, msg, t0: float) -> tuple[SparseOccupancy, str] | None:
        """The network's occupancy of the six images; None (reported) for images or calibration it cannot take."""
        from occvo_core.models.tpvformer.predictor import InvalidCameraFrameError
        from occvo_services.occupancy_model import camera_inputs

        try:
            images, K, T = camera_inputs(msg.images)
            t1 = time.perf_counter()
            with self._model_lock:
                t2 = time.perf_counter()
                idx, labels = self.model.predict(images, K, T)
                model_ms = (time.perf_counter() - t2) * 1000.0
        except (ValueError, InvalidCameraFrameError) as exc:
            self.report_error(stream, "invalid_frame", f"seq {msg.seq}: {exc}", keys.camera(stream), msg.seq)
            return None
        self.stats.observe("decode_images", (t1 - t0) * 1000.0)
        self.stats.observe("model", model_ms)
        dtype = np.uint8 if max(self.model.grid.shape) <= 256 else np.uint16
        grid = self.model.grid
        occupancy = SparseOccupancy.model_validate(
            {
                "grid": {"lower": grid.lower, "upper": grid.upper, "voxel_size": grid.voxel_size},
                "voxels": {"dtype": np.dtype(dtype).name, "shape": [len(idx), 3], "data": idx.astype(dtype).tobytes()},
                "labels": {"dtype": "uint8", "shape": [len(labels)], "data": labels.astype(np.uint8).tobytes()},
            }
        )
        return occupancy, f"model:{self.model.name}"


def _args(p) -> None:
    p.add_argument("--source", choices=["replay", "model"])
    p.add_argument("--device", choices=["auto", "cpu", "cuda"])
    p.add_argument("--checkpoint", help="TPV-Former checkpoint for the model source (occvo train-occ writes one)")
    p.add_argument("--model-weights", help="TinyOccNet state_dict for the model source, instead of --checkpoint")
    p.add_argument("--torch-threads", type=int)
    p.add_argument("--min-confidence", type=float, help="model source: voxels below this softmax confidence are free")
    p.add_argument("--min-ground-confidence", type=float, help="the same for the ground classes")
    p.add_argument(
        "--camera-mask",
        action=argparse.BooleanOptionalAction,
        help="model source: keep only the voxels the cameras' rays reach (as the shipped model is served)",
    )


def main(argv: list[str] | None = None) -> int:
    try:
        return worker_main(InferenceWorker, argv, extra_args=_args)
    except ConfigError as exc:  # a bad config or checkpoint: one line and exit 2, before anything connects
        print(f"inference worker: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
