"""The inference worker's `model` source serving a TPV-Former checkpoint, as users run it: a worker subprocess
(`python -m occvo_services.inference_worker --source model --checkpoint PATH`) on a real Zenoh router (random loopback port).
Its occupancy equals OccupancyPredictor's on the same images voxel for voxel; bad images are ErrorEvents and the
worker keeps serving; a missing, broken or mismatched checkpoint stops it at start with one line, exit 2."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import zenoh

from occvo_core.errors import ConfigError
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import CameraFrame, ErrorEvent, OccupancyFrameMsg, WorkerHealth
from occvo_services.occupancy_model import camera_inputs, encode_image
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import free_port, open_router, open_session

REPO = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A freshly initialised `tiny` TPV-Former, saved the way `occvo train-occ` saves one."""
    from occvo_core.models.tpvformer import TPVFormer, preset, save_checkpoint

    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", TPVFormer(preset("tiny")), {"preset": "tiny"})


def rendered_frames(predictor, n):
    """n frames of the synthetic town's six rendered cameras, at the checkpoint's input size (as `occvo run --from-images`)."""
    from occvo_core.cameras import CAMERA_NAMES
    from occvo_core.models.image_source import ImageOccupancySource
    from occvo_core.sim import SyntheticScene

    source = ImageOccupancySource(SyntheticScene(seed=0, frames=n), predictor)
    return [source.camera_frame(i) for i in range(n)], CAMERA_NAMES


def wire_images(images, k, e, names, encoding):
    return [encode_image(images[c], names[c], k[c], e[c], encoding) for c in range(6)]


def png16(h, w):
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((h, w), 40000, np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def start_worker(endpoint, *args):
    cmd = [
        sys.executable,
        "-m",
        "occvo_services.inference_worker",
        "--connect",
        endpoint,
        "--source",
        "model",
        "--device",
        "cpu",
        "--torch-threads",
        "1",
        "--log-level",
        "WARNING",
        *args,
    ]
    return subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(cond, timeout):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)
    return cond()


@pytest.mark.slow  # ~15 s idle (a torch worker process starts), ~45 s on a loaded 2-core machine
def test_worker_serves_the_checkpoint_equal_to_the_predictor(checkpoint):
    from occvo_core.models.tpvformer import OccupancyPredictor

    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    worker = start_worker(
        # a raw publisher that does not send again: its whole burst fits the queue (lossless answers a full one
        # stream_full, and OccVOClient sends such frames again)
        ep,
        "--checkpoint",
        str(checkpoint),
        "--worker-id",
        "inference-model-test",
        "--camera-mask",
        "--queue-size",
        "16",
    )  # starts meanwhile
    session = open_session(ep)
    try:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # as the worker (torch_threads 1): the same reduction order, the same logits
        try:
            predictor = OccupancyPredictor(checkpoint, device="cpu", camera_mask=True)
            frames, names = rendered_frames(predictor, 3)
            sent = [wire_images(*f, names, enc) for f, enc in zip(frames, ("raw_rgb8", "png", "jpeg"))]
            # the reference: the predictor called directly on what the worker decodes (jpeg is lossy)
            expected = [predictor.predict_grid(*camera_inputs(imgs)) for imgs in sent]
            unmasked = OccupancyPredictor(checkpoint, device="cpu").predict_grid(*camera_inputs(sent[0]))
            assert np.count_nonzero(expected[0] != 17) < np.count_nonzero(unmasked != 17)  # the mask took some
        finally:
            torch.set_num_threads(threads)

        got, errors = {}, []
        subs = [
            session.declare_subscriber(
                keys.occupancy("cam"),
                lambda s: got.setdefault((m := decode(s.payload.to_bytes(), OccupancyFrameMsg)).seq, m),
            ),
            session.declare_subscriber(
                keys.errors("cam"), lambda s: errors.append(decode(s.payload.to_bytes(), ErrorEvent))
            ),
        ]
        # BLOCK, as OccVOClient: with zenoh's default DROP, a camera frame (many fragments) that meets a full queue
        # towards the busy worker for 1-50 ms is dropped on the way, silently
        pub = session.declare_publisher(keys.camera("cam"), congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(lambda: pub.matching_status.matching or worker.poll() is not None, 60), (
            "worker never subscribed"
        )
        assert worker.poll() is None, worker.communicate()[1]
        # our subscribers must be known to the router before the worker publishes: probe with an image-less frame
        seq = 0
        while not errors and seq < 100:
            pub.put(encode(CameraFrame(stream="cam", seq=seq, stamp=0.0)))
            seq += 1
            wait_for(lambda: errors, 0.3)
        assert errors and "needs 6 camera images" in errors[0].message
        wait_for(lambda: len(errors) >= seq, 5)
        errors.clear()

        good = sent[0]
        flipped = np.diag([1.0, 1.0, -1.0, 1.0]) @ np.asarray(good[2].extrinsics)
        five = msgpack.unpackb(encode(CameraFrame(stream="cam", seq=0, stamp=0.0, images=good)), raw=False)
        five["images"] = five["images"][:5]
        bad = {  # what each bad frame's error must name
            "6 images": msgpack.packb(five, use_bin_type=True),
            "differ in size": [
                *good[:3],
                encode_image(np.zeros((56, 100, 3), np.uint8), names[3], np.eye(3), np.eye(4)),
                *good[4:],
            ],
            "message says": [good[0], sent[1][1].model_copy(update={"width": 208}), *good[2:]],  # a png of 200x112
            "pixel mode I;16": [
                *good[:4],
                good[4].model_copy(update={"encoding": "png", "data": png16(112, 200)}),
                good[5],
            ],
            "the bytes are PNG": [good[0].model_copy(update={"encoding": "jpeg", "data": sent[1][0].data}), *good[1:]],
            "cannot identify image": [
                *good[:5],
                good[5].model_copy(update={"encoding": "jpeg", "data": b"not a jpeg"}),
            ],
            "proper rotations": [*good[:2], good[2].model_copy(update={"extrinsics": flipped.tolist()}), *good[3:]],
        }
        seq = 0  # a new trajectory
        for images in bad.values():
            payload = (
                images
                if isinstance(images, bytes)
                else encode(CameraFrame(stream="cam", seq=seq, stamp=0.0, images=images))
            )
            pub.put(payload)
            seq += 1
        for i, imgs in enumerate(sent):  # then good frames: the worker keeps serving
            pub.put(encode(CameraFrame(stream="cam", seq=seq + i, stamp=0.5 * i, images=imgs)))
        assert wait_for(lambda: len(got) == len(sent) and len(errors) >= len(bad), 90), (
            sorted(got),
            [e.message for e in errors],
        )
        messages = [e.message for e in errors]
        for phrase in bad:
            assert sum(phrase in m for m in messages) == 1, (phrase, messages)
        assert {e.code for e in errors} == {"invalid_message", "invalid_frame"}
        for i, grid in enumerate(expected):
            msg = got[seq + i]
            assert msg.source == "model:TPVFormer[tiny]" and msg.occupancy.voxels is not None
            served = np.full(grid.shape, 17, np.uint8)  # FREE where nothing was sent
            served[tuple(msg.occupancy.voxels.to_numpy().astype(int).T)] = msg.occupancy.labels.to_numpy()
            assert np.array_equal(served, grid), f"frame {i}: {np.count_nonzero(served != grid)} voxels differ"

        health = decode(
            next(iter(session.get(keys.stats("inference-model-test"), timeout=10))).ok.payload.to_bytes(), WorkerHealth
        )
        assert health.counters["frames_out"] == len(sent) and health.stages["model"].count == len(sent)
        assert health.stages["model"].p50_ms > 0
        for s in subs:
            s.undeclare()
    finally:
        session.close()
        if worker.poll() is None:
            worker.terminate()
        out, err = worker.communicate(timeout=60)
        router.close()
    assert worker.returncode == 0, err


def test_bad_checkpoint_stops_the_worker_with_one_line(checkpoint, tmp_path):
    # mismatched: the weights of the tiny model under a config with other sizes
    payload = torch.load(checkpoint, weights_only=True)
    payload["config"]["embed_dims"] = 32
    torch.save(payload, tmp_path / "mismatched.pt")
    proc = start_worker("tcp/127.0.0.1:1", "--checkpoint", str(tmp_path / "mismatched.pt"))
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and "Traceback" not in err, err
    assert err.strip().count("\n") == 0 and "weights do not match the config" in err and "mismatched.pt" in err, err

    # in-process: the same ConfigError for a missing file, a file that is not a checkpoint, and no checkpoint at all
    from occvo_services.inference_worker import InferenceWorker

    (tmp_path / "junk.pt").write_bytes(b"not torch")
    for ckpt, phrase in (
        (tmp_path / "none.pt", "no such file"),
        (tmp_path / "junk.pt", "not a torch checkpoint"),
        (None, "needs checkpoint"),
    ):
        with pytest.raises(ConfigError, match=phrase):
            InferenceWorker(WorkerConfig(source="model", device="cpu", checkpoint=str(ckpt) if ckpt else None))


def test_old_configs_still_load(tmp_path):
    cfg = tmp_path / "inference.json5"
    cfg.write_text('{source: "model", model_weights: "w.pt", torch_threads: 2, checkpoint: "c.pt"}')
    c = WorkerConfig.load(cfg)
    assert (c.model_weights, c.checkpoint, c.torch_threads) == ("w.pt", "c.pt", 2)
    deployed = WorkerConfig.load(REPO / "deploy/inference_worker.json5")
    assert deployed.source == "replay" and deployed.checkpoint is None


def test_tiny_occ_net_weights_still_serve(tmp_path):
    """`model_weights` (TinyOccNet's state_dict) is the other network the model source takes; bad weights are refused."""
    from occvo_services.occupancy_model import TinyOccNet, load_occupancy_model

    torch.manual_seed(1)
    torch.save(TinyOccNet().state_dict(), tmp_path / "tiny_occ_net.pt")
    model = load_occupancy_model(model_weights=str(tmp_path / "tiny_occ_net.pt"), device="cpu")
    rng = np.random.default_rng(0)
    images = [
        encode_image(rng.integers(0, 255, (90, 160, 3), dtype=np.uint8), f"CAM_{i}", np.eye(3), np.eye(4), "png")
        for i in range(6)
    ]
    idx, labels = model.predict(*camera_inputs(images))
    assert model.name == "TinyOccNet" and idx.shape == (len(labels), 3) and np.all(labels < 17)
    torch.save({"not": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(ConfigError, match="not TinyOccNet weights"):
        load_occupancy_model(model_weights=str(tmp_path / "other.pt"), device="cpu")
    with pytest.raises(ConfigError, match="not both"):
        load_occupancy_model(checkpoint="c.pt", model_weights="w.pt")
