"""Which annotated box a point falls in: a box's points take its class (and, aggregated over a drive, move with it)."""

from __future__ import annotations

import numpy as np

from occvo_core.datasets.nuscenes_drive import Boxes


def boxes_in_frame(boxes: Boxes, world_to_frame: np.ndarray) -> Boxes:
    """The same boxes with centres and rotations in another frame (e.g. the ego frame of a sweep)."""
    r, t = world_to_frame[:3, :3], world_to_frame[:3, 3]
    return Boxes(
        boxes.centres @ r.T + t, r @ boxes.rotations, boxes.sizes, boxes.labels, boxes.instances, boxes.categories
    )


def box_local(points: np.ndarray, boxes: Boxes, index: int) -> np.ndarray:
    """Points (N,3) in box `index`'s own frame (x along its length, y across, z up from its centre)."""
    return (points - boxes.centres[index]) @ boxes.rotations[index]


def points_in_boxes(points: np.ndarray, boxes: Boxes, margin: float = 0.1) -> np.ndarray:
    """(N,) index of the box each point falls in, -1 for none; boxes grown by `margin` each way (annotations are
    drawn tight, a sweep's points on a box's skin scatter by a few cm)."""
    out = np.full(len(points), -1, np.int64)
    for b in range(len(boxes)):
        w, l, h = boxes.sizes[b]
        reach = np.hypot(l, w) / 2 + margin
        near = np.flatnonzero(np.abs(points[:, :2] - boxes.centres[b, :2]).max(axis=1) <= reach)
        local = box_local(points[near], boxes, b)
        half = np.array([l, w, h]) / 2 + margin
        out[near[np.all(np.abs(local) <= half, axis=1)]] = b
    return out
