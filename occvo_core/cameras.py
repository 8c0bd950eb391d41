"""The nuScenes six-camera rig: projection of ego-frame points, and a ray-casting renderer of occupancy grids.

Conventions: ego frame x forward, y left, z up (origin on the ground under the rear axle, as in nuScenes/Occ3D);
camera frame OpenCV (x right, y down, z along the optical axis); pixel (u, v) = column, row with integer pixel centres.
`cam_to_ego` maps camera coordinates to the ego frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from occvo_core.grid import CLASS_COLORS, FREE, OCC3D_GRID, GridSpec

CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_LEFT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
FULL_SIZE = (1600, 900)  # width, height of a nuScenes image

# Rounded from a nuScenes calibration: (fx, cx, cy), mounting (x, y, z) in metres, yaw in degrees.
# CAM_BACK has a shorter focal length (wider field of view) on the nuScenes car.
_NUSCENES = {
    "CAM_FRONT": ((1266.4, 816.3, 491.5), (1.70, 0.02, 1.51), 0.0),
    "CAM_FRONT_LEFT": ((1272.6, 826.6, 479.8), (1.52, 0.49, 1.51), 55.0),
    "CAM_FRONT_RIGHT": ((1260.8, 808.0, 495.3), (1.55, -0.49, 1.50), -55.0),
    "CAM_BACK": ((809.2, 829.2, 481.8), (0.03, 0.00, 1.58), 180.0),
    "CAM_BACK_LEFT": ((1256.7, 817.8, 452.0), (1.04, 0.48, 1.59), 110.0),
    "CAM_BACK_RIGHT": ((1259.5, 807.3, 501.2), (1.05, -0.48, 1.56), -110.0),
}


def camera_rotation(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Rotation camera -> ego for a camera looking horizontally along `yaw` (counter-clockwise from ego x), pitched down by `pitch`."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=1)  # columns: camera x, y, z in the ego frame


@dataclass(frozen=True)
class CameraRig:
    """Six cameras: intrinsics (6,3,3) for images of `size` (width, height) and extrinsics cam_to_ego (6,4,4)."""

    intrinsics: np.ndarray
    cam_to_ego: np.ndarray
    size: tuple[int, int] = FULL_SIZE
    names: tuple[str, ...] = CAMERA_NAMES

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    def scaled(self, width: int, height: int) -> CameraRig:
        """The same rig for images resized to (width, height); pixel centres stay consistent."""
        sx, sy = width / self.width, height / self.height
        k = self.intrinsics.copy()
        k[:, 0, 0] *= sx
        k[:, 1, 1] *= sy
        k[:, 0, 2] = (k[:, 0, 2] + 0.5) * sx - 0.5
        k[:, 1, 2] = (k[:, 1, 2] + 0.5) * sy - 0.5
        return CameraRig(k, self.cam_to_ego.copy(), (int(width), int(height)), self.names)

    def ego_to_pixel(self) -> np.ndarray:
        """(6,3,4) projection matrices K [R^T | -R^T t] from ego coordinates to homogeneous pixels."""
        ego_to_cam = np.linalg.inv(self.cam_to_ego)
        return np.einsum("nij,njk->nik", self.intrinsics, ego_to_cam[:, :3, :])

    def project(self, points: np.ndarray, min_depth: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ego points (N,3) -> pixels (6,N,2), depth along each optical axis (6,N), and in-front-and-in-image (6,N)."""
        pts = np.asarray(points, dtype=np.float64)
        homo = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
        cam = np.einsum("cij,nj->cni", self.ego_to_pixel(), homo)
        depth = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = cam[..., :2] / depth[..., None]
        in_image = (
            (uv[..., 0] >= -0.5)
            & (uv[..., 0] < self.width - 0.5)
            & (uv[..., 1] >= -0.5)
            & (uv[..., 1] < self.height - 0.5)
        )
        return uv, depth, (depth > min_depth) & in_image

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions in the ego frame through every pixel centre, (6, H, W, 3)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        pix = np.stack([u, v, np.ones_like(u)], axis=-1)
        cam = np.einsum("cij,hwj->chwi", np.linalg.inv(self.intrinsics), pix)
        ego = np.einsum("cij,chwj->chwi", self.cam_to_ego[:, :3, :3], cam)
        return ego / np.linalg.norm(ego, axis=-1, keepdims=True)


def nuscenes_rig(width: int = FULL_SIZE[0], height: int = FULL_SIZE[1]) -> CameraRig:
    """The nuScenes surround rig in CAMERA_NAMES order, scaled to (width, height)."""
    intrinsics = np.zeros((6, 3, 3))
    cam_to_ego = np.tile(np.eye(4), (6, 1, 1))
    for i, name in enumerate(CAMERA_NAMES):
        (f, cx, cy), t, yaw = _NUSCENES[name]
        intrinsics[i] = [[f, 0, cx], [0, f, cy], [0, 0, 1]]
        cam_to_ego[i, :3, :3] = camera_rotation(yaw)
        cam_to_ego[i, :3, 3] = t
    rig = CameraRig(intrinsics, cam_to_ego)
    return rig if (width, height) == FULL_SIZE else rig.scaled(width, height)


# ---------------------------------------------------------------------------------------------------------------------
# Renderer


@dataclass(frozen=True)
class RenderStyle:
    """Appearance knobs: the images must not be separable by colour alone."""

    fog_distance_m: float = 55.0  # fog weight 1 - exp(-depth / fog_distance)
    fog_color: tuple[float, float, float] = (190.0, 195.0, 200.0)
    noise_sigma: float = 8.0  # per-pixel Gaussian noise, 0..255 scale
    texture: float = 0.12  # per-voxel brightness jitter
    colour_jitter: float = 0.10  # per-image gain jitter (exposure / white balance)
    sun: tuple[float, float, float] = (0.4, 0.3, 0.87)


@dataclass
class RenderedFrame:
    images: np.ndarray  # (6, H, W, 3) uint8 RGB
    depth: np.ndarray  # (6, H, W) float32 ray length to the first occupied voxel, inf where none
    labels: np.ndarray  # (6, H, W) uint8 class of the first occupied voxel, 255 where none
    camera_mask: np.ndarray  # (200, 200, 16) bool: voxels the rays traverse, up to and including the first occupied one


@njit(cache=True)
def _cast_rays(origins, dirs, semantics, lower, voxel, out_label, out_depth, out_axis, out_cell, visible):
    """3D DDA (Amanatides-Woo) through the grid for every ray; marks traversed voxels visible (Occ3D camera mask)."""
    nx, ny, nz = semantics.shape
    upper = np.array([lower[0] + nx * voxel, lower[1] + ny * voxel, lower[2] + nz * voxel])
    dims = np.array([nx, ny, nz])
    ncam, h, w = dirs.shape[0], dirs.shape[1], dirs.shape[2]
    for c in range(ncam):
        o = origins[c]
        for r in range(h):
            for q in range(w):
                d = dirs[c, r, q]
                out_label[c, r, q] = 255
                out_depth[c, r, q] = np.inf
                out_axis[c, r, q] = 0
                # Slab test: parametric interval of the ray inside the grid box.
                t0, t1, enter_axis = 0.0, np.inf, -1
                for a in range(3):
                    if abs(d[a]) < 1e-12:
                        if o[a] < lower[a] or o[a] >= upper[a]:
                            t1 = -1.0
                        continue
                    ta, tb = (lower[a] - o[a]) / d[a], (upper[a] - o[a]) / d[a]
                    if ta > tb:
                        ta, tb = tb, ta
                    if ta > t0:
                        t0, enter_axis = ta, a
                    t1 = min(t1, tb)
                if t1 <= t0:
                    continue
                idx = np.empty(3, np.int64)
                step = np.empty(3, np.int64)
                tmax = np.empty(3)
                tdelta = np.empty(3)
                for a in range(3):
                    p = o[a] + d[a] * (t0 + 1e-9)
                    i = int(np.floor((p - lower[a]) / voxel))
                    idx[a] = min(max(i, 0), dims[a] - 1)
                    if d[a] > 0:
                        step[a] = 1
                        tmax[a] = (lower[a] + (idx[a] + 1) * voxel - o[a]) / d[a]
                        tdelta[a] = voxel / d[a]
                    elif d[a] < 0:
                        step[a] = -1
                        tmax[a] = (lower[a] + idx[a] * voxel - o[a]) / d[a]
                        tdelta[a] = -voxel / d[a]
                    else:
                        step[a] = 0
                        tmax[a] = np.inf
                        tdelta[a] = np.inf
                t, axis = t0, enter_axis
                while True:
                    visible[idx[0], idx[1], idx[2]] = True
                    lab = semantics[idx[0], idx[1], idx[2]]
                    if lab != 17:
                        out_label[c, r, q] = lab
                        out_depth[c, r, q] = t
                        out_axis[c, r, q] = (axis + 1) * (-step[axis]) if axis >= 0 else 0
                        out_cell[c, r, q, 0] = idx[0]
                        out_cell[c, r, q, 1] = idx[1]
                        out_cell[c, r, q, 2] = idx[2]
                        break
                    a = 0
                    if tmax[1] < tmax[a]:
                        a = 1
                    if tmax[2] < tmax[a]:
                        a = 2
                    t = tmax[a]
                    idx[a] += step[a]
                    if idx[a] < 0 or idx[a] >= dims[a]:
                        break
                    tmax[a] += tdelta[a]
                    axis = a


def render(
    semantics: np.ndarray,
    rig: CameraRig,
    style: RenderStyle = RenderStyle(),
    rng: np.random.Generator | int | None = 0,
    grid: GridSpec = OCC3D_GRID,
) -> RenderedFrame:
    """Ray cast a dense ego-frame label grid (uint8, FREE = empty) from each camera of `rig`.

    Colour = class colour x (ambient + sun diffuse on the hit face) x per-voxel texture, darkened at voxel edges,
    then distance fog, per-image gain jitter and pixel noise. Rays that leave the grid show sky above the horizon
    and a far ground colour below it.
    """
    semantics = np.ascontiguousarray(semantics, dtype=np.uint8)
    if semantics.shape != grid.shape:
        raise ValueError(f"semantics grid has shape {semantics.shape}, expected {grid.shape}")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    dirs = rig.ray_directions()
    origins = np.ascontiguousarray(rig.cam_to_ego[:, :3, 3])
    n, h, w = dirs.shape[:3]
    label = np.empty((n, h, w), np.uint8)
    depth = np.empty((n, h, w), np.float64)
    axis = np.zeros((n, h, w), np.int8)
    cell = np.zeros((n, h, w, 3), np.int64)
    visible = np.zeros(grid.shape, np.bool_)
    _cast_rays(
        origins,
        dirs,
        semantics,
        np.asarray(grid.lower, np.float64),
        float(grid.voxel_size),
        label,
        depth,
        axis,
        cell,
        visible,
    )

    hit = label != 255
    colours = CLASS_COLORS.astype(np.float32)
    dirs = dirs.astype(np.float32)
    depth32 = depth.astype(np.float32)
    # Lambert shading on the hit face: normal = signed axis recorded by the DDA.
    sun = np.asarray(style.sun, np.float32)
    sun = sun / np.linalg.norm(sun)
    a = np.abs(axis.astype(np.int64))
    normal_dot = np.where(a > 0, np.sign(axis) * sun[np.clip(a - 1, 0, 2)], 0.5)
    shade = 0.45 + 0.55 * np.clip(normal_dot, 0.0, 1.0)
    # Per-voxel texture from a hash of the voxel index: neighbouring voxels of one class differ a little.
    hsh = (cell[..., 0] * 73856093) ^ (cell[..., 1] * 19349663) ^ (cell[..., 2] * 83492791)
    tex = (1.0 + style.texture * ((hsh % 1000) / 500.0 - 1.0)).astype(np.float32)
    # Darken voxel edges so shapes are visible inside uniform regions.
    p = origins.astype(np.float32)[:, None, None, :] + dirs * np.where(hit, depth32, 0.0)[..., None]
    frac = (p - np.asarray(grid.lower, np.float32)) / np.float32(grid.voxel_size)
    frac = np.abs(frac - np.round(frac))  # distance to the nearest voxel boundary, in voxels
    on_face = np.ones_like(frac, dtype=bool)
    on_face[np.arange(3)[None, None, None, :] == (a[..., None] - 1)] = False  # ignore the axis of the face itself
    edge = np.where(on_face, frac, 1.0).min(axis=-1) < 0.06
    base = colours[label.clip(0, FREE)]
    base = np.where(label[..., None] == 0, 40.0, base)  # "others" is black in the palette: make it dark grey, not void
    rgb = base * (shade * tex * np.where(edge, 0.8, 1.0)).astype(np.float32)[..., None]
    # Background: sky gradient above the horizon, far ground below it.
    up = dirs[..., 2]
    zenith, horizon = np.array([120, 165, 225], np.float32), np.array([205, 215, 230], np.float32)
    sky = zenith + (horizon - zenith) * np.exp(-8 * np.clip(up, 0, 1))[..., None]
    ground = np.array([95, 92, 88], np.float32)
    background = np.where((up > 0)[..., None], sky, ground)
    rgb = np.where(hit[..., None], rgb, background)
    # Distance fog: far background is fully fogged.
    fog_w = 1.0 - np.exp(-np.where(hit, depth32, np.where(up > 0, 0.0, 1e3)) / np.float32(style.fog_distance_m))
    rgb = rgb * (1 - fog_w[..., None]) + np.asarray(style.fog_color, np.float32) * fog_w[..., None]
    gain = (1.0 + style.colour_jitter * rng.uniform(-1, 1, size=(n, 1, 1, 3))).astype(np.float32)
    noise = rng.standard_normal(size=rgb.shape, dtype=np.float32) * np.float32(style.noise_sigma)
    rgb = rgb * gain + noise
    images = np.clip(rgb, 0, 255).astype(np.uint8)
    return RenderedFrame(images, depth.astype(np.float32), label, visible)
