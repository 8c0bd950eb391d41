"""Pictures a person can check the labels by: a keyframe's LiDAR points drawn over each camera's image, coloured by
their class, and from above the LiDAR labels beside the camera model's prediction."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES
from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.grid import CLASS_COLORS, FREE
from occvo_core.lidar.boxes import boxes_in_frame
from occvo_core.lidar.sweep import label_points, off_the_car

HALF = 2  # camera pictures at half size: 800x450
DOT_COLORS = CLASS_COLORS.copy()
DOT_COLORS[0] = (90, 90, 90)  # "others" is black in the palette: grey, to show on a dark image


def camera_pictures(drive: NuScenesDrive, index: int, out_dir: Path) -> list[Path]:
    """One PNG a camera: the keyframe's own sweep (labelled as make-occupancy labels it) moved to the ego at the
    image's stamp, projected by the calibrated camera, on the image."""
    from PIL import Image, ImageDraw

    k = drive[index]
    points = drive.lidar_in_ego(index)
    points = points[off_the_car(points)]
    labels, _ = label_points(points, boxes_in_frame(drive.boxes(index), np.linalg.inv(k.ego_pose)))
    rig, paths = drive.rig(index), []
    for c, name in enumerate(CAMERA_NAMES):
        moved = points @ drive.ego_at_camera(index, c)[:3, :3].T + drive.ego_at_camera(index, c)[:3, 3]
        uv, depth, seen = rig.project(moved)
        with Image.open(k.files[c]) as im:
            picture = im.convert("RGB").resize((rig.width // HALF, rig.height // HALF), Image.BILINEAR)
        draw = ImageDraw.Draw(picture)
        order = np.argsort(-depth[c][seen[c]])  # far first: near points drawn on top
        for (u, v), label in zip(uv[c][seen[c]][order] / HALF, labels[seen[c]][order]):
            draw.ellipse((u - 1.5, v - 1.5, u + 1.5, v + 1.5), fill=tuple(int(x) for x in DOT_COLORS[label]))
        paths.append(out_dir / f"{index:03d}_{name}.png")
        picture.save(paths[-1])
    return paths


def top_view(semantics: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(200,200,3) uint8 from above, ego x up and y left: each column's highest occupied voxel in its class colour."""
    occupied = semantics != FREE if mask is None else (semantics != FREE) & mask
    top = occupied.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    label = np.take_along_axis(semantics, top[..., None], axis=2)[..., 0]
    image = np.where(occupied.any(axis=2)[..., None], DOT_COLORS[label], 30).astype(np.uint8)
    return image[::-1, ::-1]  # rows: x from +40 m down; columns: y from +40 m (left) to the right


def top_pictures(panels: dict[str, np.ndarray], path: Path, scale: int = 3) -> Path:
    """Top views side by side, each captioned."""
    from PIL import Image, ImageDraw

    images = [
        Image.fromarray(p).resize((p.shape[1] * scale, p.shape[0] * scale), Image.NEAREST) for p in panels.values()
    ]
    out = Image.new("RGB", (sum(i.width for i in images) + 10 * (len(images) - 1), images[0].height + 20), "white")
    draw, x = ImageDraw.Draw(out), 0
    for caption, image in zip(panels, images):
        out.paste(image, (x, 20))
        draw.text((x + 4, 4), caption, fill="black")
        cx, cy = x + image.width // 2, 20 + image.height // 2  # the ego at the grid's centre, facing up
        draw.polygon([(cx, cy - 6), (cx - 4, cy + 4), (cx + 4, cy + 4)], fill="red")
        x += image.width + 10
    out.save(path)
    return path
