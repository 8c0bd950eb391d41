"""streams_load.py's scenes, rendered once into a cache of voxel indices, and its streams: each sends its scene open
loop at the camera rate and records when every pose comes back."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from occvo_core.grid import OCC3D_GRID
from occvo_schemas.codec import CodecError, decode
from occvo_schemas.models import Array, CameraFrame, GridSpecModel, PoseEstimate, SparseOccupancy


def _render(args: tuple[int, int, float, str]) -> str:
    """Render one synthetic scene to an npz of voxel indices (synthetic frames lie on the grid: nothing is lost)."""
    seed, frames, rate, path = args
    os.nice(10)  # leave the cores to whatever else runs on the machine
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=seed, frames=frames, rate_hz=rate)
    idx, labels, counts, stamps = [], [], [], []
    for i in range(frames):
        f = scene[i]
        idx.append(OCC3D_GRID.indices_of(f.points).astype(np.uint8))
        labels.append(f.labels.astype(np.uint8))
        counts.append(len(f.labels))
        stamps.append(f.stamp)
        scene._frames.clear()  # the scene caches frames; we keep only the compact copy
    tmp = path + ".tmp.npz"
    np.savez(
        tmp, idx=np.concatenate(idx), labels=np.concatenate(labels), counts=np.array(counts), stamps=np.array(stamps)
    )
    os.replace(tmp, path)
    return path


def _cached(cache_dir: Path, seed: int, frames: int, rate: float) -> Path:
    """The shortest cached render of this seed with at least `frames` frames (its first frames are a drive too)."""
    have = []
    for p in cache_dir.glob(f"synthetic-{seed}-*f-{rate:g}hz.npz"):
        try:
            n = int(p.name.split("-")[2][:-1])
        except ValueError:
            continue
        if n >= frames:
            have.append((n, p))
    return min(have)[1] if have else cache_dir / f"synthetic-{seed}-{frames}f-{rate:g}hz.npz"


def load_scenes(
    seeds: list[int], frames: int, rate: float, cache_dir: Path, jobs: int
) -> dict[int, list[SparseOccupancy]]:
    cache_dir.mkdir(parents=True, exist_ok=True)
    paths = {s: _cached(cache_dir, s, frames, rate) for s in seeds}
    todo = [(s, frames, rate, str(p)) for s, p in paths.items() if not p.exists()]
    if todo:
        t0 = time.perf_counter()
        print(f"rendering {len(todo)} scenes of {frames} frames into {cache_dir} ({jobs} processes)...", flush=True)
        with ProcessPoolExecutor(jobs) as pool:
            list(pool.map(_render, todo))
        print(f"rendered in {time.perf_counter() - t0:.0f} s", flush=True)
    grid = GridSpecModel.from_grid(OCC3D_GRID)
    out = {}
    for s, p in paths.items():
        with np.load(p) as z:  # an npz reads an array on every z[...]: once each
            idx, labels, ends = z["idx"], z["labels"], np.cumsum(z["counts"])
        out[s] = [
            SparseOccupancy(grid=grid, voxels=Array.from_numpy(idx[a:b]), labels=Array.from_numpy(labels[a:b]))
            for a, b in list(zip(np.r_[0, ends[:-1]], ends))[:frames]
        ]
    return out


# ---------------------------------------------------------------- one run


class Stream:
    """One stream's sender: frame i leaves at t0 + (i + offset) / rate, open loop."""

    def __init__(self, name: str, frames: list[SparseOccupancy], offset: float):
        self.name, self.frames, self.offset = name, frames, offset
        self.due = np.zeros(len(frames))  # wall clock the frame is due (a camera would capture it then)
        self.sent_at = np.full(len(frames), np.nan)  # wall clock at send (the message's sent_at)
        self.lag = np.full(len(frames), np.nan)  # send time - schedule, s
        self.build_ms = np.full(len(frames), np.nan)  # message build
        self.put_ms = np.full(len(frames), np.nan)  # encode and put (waits under lossless backpressure)
        self.recv_at: dict[int, float] = {}
        self.timings: dict[int, dict[str, float]] = {}  # seq -> the pose's timings_ms (where its time went)
        self.last_sent = -1
        self.errors: dict[str, int] = {}
        self.turned_away = self.resends = 0  # stream_full answers and frames sent again (the client's counts)

    def on_pose(self, sample) -> None:
        t = time.time()
        try:
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
        except CodecError:
            return
        self.recv_at.setdefault(pose.seq, t)
        self.timings.setdefault(pose.seq, pose.timings_ms)

    def newest_back(self) -> int:
        return max(self.recv_at, default=-1)

    def send_all(self, client, t0: float, rate: float, stop: threading.Event) -> None:
        """Until every frame is sent or `stop` (the end of the window), through the product's client (OccVOClient):
        a frame a full queue turned away (stream_full) goes again and the frames after it wait in the client, so
        under lossless backpressure the schedule slips (send lag) and frames due after the window are never sent."""
        self.due = t0 + (np.arange(len(self.frames)) + self.offset) / rate
        for i, occ in enumerate(self.frames):
            due = self.due[i]
            while not stop.is_set() and time.time() < due:
                time.sleep(min(0.05, max(0.0, due - time.time())))
            if stop.is_set():
                return
            a = time.perf_counter()
            now = time.time()
            frame = CameraFrame(stream=self.name, seq=i, stamp=i / rate, gt_occupancy=occ, sent_at=now)
            b = time.perf_counter()
            client.publish(frame)  # encoded, held while the stream's frames are turned away, put
            self.put_ms[i] = (time.perf_counter() - b) * 1000.0
            self.build_ms[i] = (b - a) * 1000.0
            self.sent_at[i], self.lag[i] = now, now - due
            self.last_sent = i
