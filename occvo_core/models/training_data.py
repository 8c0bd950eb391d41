"""Training data for TPV-Former: synthetic scenes' frames rendered into the six cameras (images, true occupancy,
depth and pixel labels for the auxiliary losses), rendered once into a cache and reused."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from occvo_core.cameras import CameraRig, RenderStyle, nuscenes_rig, render


@dataclass
class Sample:
    images: torch.Tensor  # (6, 3, H, W) float in [0, 1]
    intrinsics: torch.Tensor  # (6, 3, 3)
    cam_to_ego: torch.Tensor  # (6, 4, 4)
    semantics: np.ndarray  # (200, 200, 16) uint8
    camera_mask: np.ndarray  # (200, 200, 16) bool
    depth: np.ndarray | None = None  # (6, H, W) float32 ray length to the first occupied voxel, inf where none
    pixel_labels: np.ndarray | None = None  # (6, H, W) uint8 class of that voxel, 255 where none
    sparse: bool = False  # a real camera's targets: labels known only inside mask_camera, depth only at LiDAR returns


def _sample(images_uint8, rig: CameraRig, semantics, camera_mask, depth=None, pixel_labels=None) -> Sample:
    images = torch.from_numpy(np.ascontiguousarray(images_uint8)).permute(0, 3, 1, 2).float().div_(255.0)
    return Sample(
        images,
        torch.tensor(rig.intrinsics, dtype=torch.float32),
        torch.tensor(rig.cam_to_ego, dtype=torch.float32),
        np.asarray(semantics, np.uint8),
        np.asarray(camera_mask, bool),
        depth,
        pixel_labels,
    )


def make_sample(
    semantics: np.ndarray, rig: CameraRig, rng: int | np.random.Generator = 0, style: RenderStyle = RenderStyle()
) -> Sample:
    frame = render(semantics, rig, style, rng)
    return _sample(frame.images, rig, semantics, frame.camera_mask, frame.depth, frame.labels)


class SyntheticOccDataset:
    """Frames of SyntheticScene(seed) for each seed; each rendered on first use.

    With `cache_dir`, rendered frames are kept on disk (one .npz each, named by seed, frame and image size) and read
    back by later runs, so training time goes to training steps rather than to ray casting. In memory at most
    `memory_frames` are kept (the most recently used): frames of a few MB each, and thousands of them
    took a whole machine's memory (the training run was killed). A frame let go is read from disk again, or rendered
    again without `cache_dir`.
    """

    def __init__(
        self,
        seeds: list[int],
        frames: int,
        rig: CameraRig,
        stride: int = 1,
        cache_dir: str | Path | None = None,
        first: int = 0,
        memory_frames: int = 512,
    ):
        from occvo_core.sim import SyntheticScene  # the sim is only needed for synthetic training/eval

        self.seeds, self.rig = list(seeds), rig
        self._scene_cls, self._frames, self._stride = SyntheticScene, frames, stride
        self._scenes: dict[int, object] = {}
        self.index = [(s, i) for s in self.seeds for i in range(first, frames, stride)]
        self._cache: OrderedDict[int, Sample] = OrderedDict()
        self.memory_frames = max(1, memory_frames)
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None

    def __len__(self) -> int:
        return len(self.index)

    def _disk_path(self, seed: int, i: int) -> Path:
        w, h = self.rig.size
        return self.cache_dir / f"seed{seed}_of{self._frames}_frame{i}_{w}x{h}_v2.npz"

    def __getitem__(self, k: int) -> Sample:
        if k in self._cache:
            self._cache.move_to_end(k)
            return self._cache[k]
        while len(self._cache) >= self.memory_frames:
            self._cache.popitem(last=False)
        seed, i = self.index[k]
        path = self._disk_path(seed, i) if self.cache_dir is not None else None
        if path is not None and path.is_file():
            with np.load(path) as z:
                self._cache[k] = _sample(
                    z["images"], self.rig, z["semantics"], z["camera_mask"], z["depth"], z["labels"]
                )
            return self._cache[k]
        if seed not in self._scenes:
            self._scenes[seed] = self._scene_cls(seed=seed, frames=self._frames)
        semantics = np.asarray(self._scenes[seed].true_grid(i), np.uint8)
        frame = render(semantics, self.rig, RenderStyle(), seed * 1000 + i)
        self._cache[k] = _sample(frame.images, self.rig, semantics, frame.camera_mask, frame.depth, frame.labels)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez_compressed(
                tmp,
                images=frame.images,
                semantics=semantics,
                camera_mask=frame.camera_mask,
                depth=frame.depth.astype(np.float32),
                labels=frame.labels,
            )
            tmp.replace(path)
        return self._cache[k]


def _render_seed(job: tuple[int, int, int, tuple[int, int], str]) -> int:
    seed, frames, stride, size, cache_dir = job
    # on disk once rendered: a worker holds one frame at a time
    data = SyntheticOccDataset([seed], frames, nuscenes_rig(*size), stride=stride, cache_dir=cache_dir, memory_frames=1)
    for k in range(len(data)):
        data[k]
    return len(data)


def prerender(
    seeds: list[int],
    frames: int,
    stride: int,
    input_size: tuple[int, int],
    cache_dir: str | Path,
    jobs: int = 2,
    progress: bool = True,
) -> int:
    """Render every training frame of `seeds` into cache_dir (frames already there are kept), in `jobs` processes."""
    from concurrent.futures import ProcessPoolExecutor

    todo = [(s, frames, stride, tuple(input_size), str(cache_dir)) for s in seeds]
    with ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        return sum(
            tqdm(pool.map(_render_seed, todo), total=len(todo), desc="prerender", unit="seed", disable=not progress)
        )


# -- training -------------------------------------------------------------------------------------------------------
