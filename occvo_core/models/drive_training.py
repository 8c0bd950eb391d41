"""Training samples from a real drive: each keyframe's six JPEGs, its Occ3D-style LiDAR labels (voxel targets inside
mask_camera) and its own LiDAR sweep projected into every image (a sparse per-pixel depth and class target), with
the augmentation a real camera needs: exposure, colour, and a small crop and zoom whose intrinsics change to match.

The images are kept at twice the network's input size (a crop then still has pixels to spare) and everything a
sample needs is held in arrays, so that `save`/`load` carry a drive's training frames where the drive is not (the
GPU check's cache).

    frames = DriveFrames.from_drive(NuScenesDrive(root), labels_root, range(17), (200, 112))
    sample = frames.sample(0, np.random.default_rng(0))      # augmented
    sample = frames.sample(0)                                 # as recorded, resized
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from occvo_core.cameras import CameraRig
from occvo_core.errors import DatasetError
from occvo_core.models.training_data import Sample

NO_LABEL = 255


@dataclass(frozen=True)
class Augment:
    """Ranges drawn per camera. zoom: the crop is 1/zoom of the stored image each way (1 = none)."""

    exposure: tuple[float, float] = (0.6, 1.5)  # a gain on linear intensity
    gamma: tuple[float, float] = (0.8, 1.25)
    white_balance: float = 0.1  # per-channel gain in 1 +- this
    saturation: tuple[float, float] = (0.7, 1.3)
    zoom: tuple[float, float] = (1.0, 1.25)
    noise: float = 0.01


def crop_rig(rig: CameraRig, boxes: np.ndarray, width: int, height: int) -> CameraRig:
    """The rig of images cut to `boxes` (6, 4: left, top, right, bottom in pixel-edge coordinates of rig's images)
    and each resized to (width, height): a pixel centre u of the crop maps back to left + (u + 0.5) * bw / width - 0.5."""
    k = rig.intrinsics.copy()
    sx, sy = width / (boxes[:, 2] - boxes[:, 0]), height / (boxes[:, 3] - boxes[:, 1])
    k[:, 0, 0] *= sx
    k[:, 1, 1] *= sy
    k[:, 0, 2] = (k[:, 0, 2] + 0.5 - boxes[:, 0]) * sx - 0.5
    k[:, 1, 2] = (k[:, 1, 2] + 0.5 - boxes[:, 1]) * sy - 0.5
    return CameraRig(k, rig.cam_to_ego.copy(), (int(width), int(height)), rig.names)


def photometric(images: torch.Tensor, rng: np.random.Generator, aug: Augment) -> torch.Tensor:
    """(6, 3, H, W) in [0, 1]: each camera its own exposure, gamma, white balance, saturation and noise (real
    cameras of one rig differ in all of them)."""
    n = images.shape[0]

    def draw(lo_hi, shape=(n, 1, 1, 1)):
        return torch.from_numpy(rng.uniform(*lo_hi, size=shape).astype(np.float32))

    linear = images.clamp(0, 1) ** 2.2  # exposure acts on light, not on the encoded values
    wb = 1 + aug.white_balance * draw((-1.0, 1.0), (n, 3, 1, 1))
    out = (linear * draw(aug.exposure) * wb).clamp(0, 1) ** (1 / 2.2)
    out = out ** draw(aug.gamma)
    grey = out.mean(1, keepdim=True)
    out = grey + (out - grey) * draw(aug.saturation)
    if aug.noise:
        out = out + aug.noise * torch.from_numpy(rng.standard_normal(out.shape).astype(np.float32))
    return out.clamp(0, 1)


def lidar_targets(points: list[np.ndarray], labels: list[np.ndarray], rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """Per camera c, `points[c]` (N, 3) in the ego frame at that camera's stamp with classes `labels[c]` -> the ray
    length to the nearest point landing in each pixel (6, H, W) float32, inf where none, and its class (255: none).
    Ray length along the pixel centre's ray, the renderer's convention (depth_loss turns it back into depth)."""
    w, h = rig.size
    depth = np.full((6, h, w), np.inf, np.float32)
    cls = np.full((6, h, w), NO_LABEL, np.uint8)
    for c in range(6):
        uv, z, ok = rig.project(points[c])
        uv, z, lab = uv[c][ok[c]], z[c][ok[c]], labels[c][ok[c]]
        u, v = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, z, lab = u[inside], v[inside], z[inside], lab[inside]
        k = rig.intrinsics[c]
        ray = z * np.sqrt(((u - k[0, 2]) / k[0, 0]) ** 2 + ((v - k[1, 2]) / k[1, 1]) ** 2 + 1)
        order = np.argsort(-ray)  # far first: the nearest point of a pixel is written last and stays
        flat = v[order] * w + u[order]
        depth[c].reshape(-1)[flat] = ray[order]
        cls[c].reshape(-1)[flat] = lab[order]
    return depth, cls


class DriveFrames:
    """A drive's keyframes as training samples; arrays only (see the module's doc)."""

    def __init__(self, arrays: dict[str, np.ndarray], input_size: tuple[int, int]):
        self.arrays, self.input_size = arrays, (int(input_size[0]), int(input_size[1]))
        self.keyframes = [int(i) for i in arrays["keyframes"]]

    @classmethod
    def from_drive(
        cls,
        drive,
        labels_root: str | Path,
        keyframes,
        input_size: tuple[int, int],
        stored: tuple[int, int] | None = None,
    ) -> DriveFrames:
        """`stored`: the images' kept size (default twice `input_size`: a crop still has pixels to spare)."""
        from PIL import Image

        from occvo_core.datasets.occ3d_write import label_path
        from occvo_core.lidar.boxes import boxes_in_frame
        from occvo_core.lidar.sweep import label_points, off_the_car

        keyframes = list(keyframes)
        width, height = stored or (2 * int(input_size[0]), 2 * int(input_size[1]))
        images = np.empty((len(keyframes), 6, height, width, 3), np.uint8)
        semantics = np.empty((len(keyframes), 200, 200, 16), np.uint8)
        masks = np.empty((len(keyframes), 200, 200, 16), bool)
        intrinsics, cam_to_ego, points, point_labels, counts, moves = [], [], [], [], [], []
        for n, i in enumerate(keyframes):
            k = drive[i]
            path = label_path(Path(labels_root), drive.name, k.token)
            if not path.is_file():
                raise DatasetError(path, f"no labels for keyframe {i}: make them with occvo make-occupancy")
            with np.load(path) as z:
                semantics[n], masks[n] = z["semantics"], z["mask_camera"].astype(bool)
            for c, f in enumerate(k.files):
                with Image.open(f) as im:
                    images[n, c] = np.asarray(im.convert("RGB").resize((width, height), Image.BILINEAR))
            rig = drive.rig(i).scaled(width, height)
            intrinsics.append(rig.intrinsics)
            cam_to_ego.append(rig.cam_to_ego)
            sweep = drive.lidar_in_ego(i)
            sweep = sweep[off_the_car(sweep)]
            lab, _ = label_points(sweep, boxes_in_frame(drive.boxes(i), np.linalg.inv(k.ego_pose)))
            points.append(sweep.astype(np.float32))
            point_labels.append(lab)
            counts.append(len(sweep))
            moves.append([drive.ego_at_camera(i, c) for c in range(6)])  # the car moves between sweep and image
        arrays = {
            "scene": np.asarray(drive.name),
            "keyframes": np.asarray(keyframes, np.int64),
            "images": images,
            "intrinsics": np.asarray(intrinsics),
            "cam_to_ego": np.asarray(cam_to_ego),
            "semantics": semantics,
            "mask_camera": masks,
            "points": np.concatenate(points),
            "point_labels": np.concatenate(point_labels),
            "point_counts": np.asarray(counts, np.int64),
            "ego_at_camera": np.asarray(moves),  # (n, 6, 4, 4): ego at the sweep -> ego at each image's stamp
        }
        return cls(arrays, input_size)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, input_size=np.asarray(self.input_size), **self.arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path, input_size: tuple[int, int] | None = None) -> DriveFrames:
        try:
            with np.load(path) as z:
                arrays = {k: z[k] for k in z.files if k != "input_size"}
                size = tuple(int(v) for v in z["input_size"])
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"not a drive-frames file ({type(exc).__name__}: {exc})") from None
        return cls(arrays, input_size or size)

    def __len__(self) -> int:
        return len(self.keyframes)

    def rig(self, n: int) -> CameraRig:
        images = self.arrays["images"]
        return CameraRig(self.arrays["intrinsics"][n], self.arrays["cam_to_ego"][n], (images.shape[3], images.shape[2]))

    def points(self, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Keyframe n's sweep in the ego frame at each camera's stamp, and the points' classes."""
        end = int(np.sum(self.arrays["point_counts"][: n + 1]))
        start = end - int(self.arrays["point_counts"][n])
        sweep = self.arrays["points"][start:end].astype(np.float64)
        moves = self.arrays["ego_at_camera"][n]
        return [sweep @ t[:3, :3].T + t[:3, 3] for t in moves], [self.arrays["point_labels"][start:end]] * 6

    def sample(self, n: int, rng: np.random.Generator | None = None, aug: Augment = Augment()) -> Sample:
        """Keyframe n (position in `keyframes`) at the input size: augmented with `rng`, else as recorded."""
        import torch.nn.functional as F

        width, height = self.input_size
        stored = self.rig(n)
        sw, sh = stored.size
        if rng is None:
            boxes = np.tile([0.0, 0.0, sw, sh], (6, 1))
        else:
            zoom = rng.uniform(*aug.zoom, size=6)
            bw, bh = sw / zoom, sh / zoom
            left, top = rng.uniform(0, sw - bw), rng.uniform(0, sh - bh)
            boxes = np.stack([left, top, left + bw, top + bh], 1)
        rig = crop_rig(stored, boxes, width, height)
        x = torch.from_numpy(self.arrays["images"][n]).permute(0, 3, 1, 2).float().div_(255.0)
        # each output pixel centre sampled where crop_rig says it comes from (bilinear, pixel-edge coordinates)
        u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
        v = (torch.arange(height, dtype=torch.float64) + 0.5) / height
        b = torch.from_numpy(boxes)
        gx = (b[:, 0:1] + u[None] * (b[:, 2:3] - b[:, 0:1])) / sw * 2 - 1  # (6, W) in grid_sample's [-1, 1]
        gy = (b[:, 1:2] + v[None] * (b[:, 3:4] - b[:, 1:2])) / sh * 2 - 1
        grid = torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), -1).float()
        if (b[:, 2] - b[:, 0]).min().item() / width >= 1.5:  # shrinking: average first so that nothing aliases
            x = F.avg_pool2d(x, 2)
        x = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
        if rng is not None:
            x = photometric(x, rng, aug)
        depth, labels = lidar_targets(*self.points(n), rig)
        return Sample(
            x.contiguous(),
            torch.tensor(rig.intrinsics, dtype=torch.float32),
            torch.tensor(rig.cam_to_ego, dtype=torch.float32),
            self.arrays["semantics"][n],
            self.arrays["mask_camera"][n],
            depth,
            labels,
            sparse=True,
        )
