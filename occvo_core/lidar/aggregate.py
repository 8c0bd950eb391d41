"""A drive's sweeps aggregated into one keyframe, as Occ3D aggregates them: static points (in no box) placed in the
world by the ground-truth ego poses, each box's points carried with the box (by instance token) to where the same
instance's box is at the keyframe; an instance without a box at the keyframe drops its points. Labels come from each
sweep's own frame (label_points: box class, ground, manmade). Ground-truth poses: labels only, never odometry input."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.lidar.boxes import box_local, boxes_in_frame
from occvo_core.lidar.sweep import label_points, off_the_car


@dataclass(frozen=True)
class SweepPoints:
    """One sweep's labelled points: the static ones in the world frame, the boxed ones in their box's own frame."""

    origin: np.ndarray  # (3,) the LiDAR's centre in the world frame
    static: np.ndarray  # (N, 3) world
    static_labels: np.ndarray  # (N,) uint8
    in_box: dict[str, np.ndarray]  # instance token -> (M, 3) in the box's frame


def sweep_points(drive: NuScenesDrive, index: int) -> SweepPoints:
    k = drive[index]
    points = drive.lidar_in_ego(index)
    points = points[off_the_car(points)]
    boxes = boxes_in_frame(drive.boxes(index), np.linalg.inv(k.ego_pose))
    labels, box = label_points(points, boxes)
    static = box < 0
    world = points[static] @ k.ego_pose[:3, :3].T + k.ego_pose[:3, 3]
    carried = {boxes.instances[b]: box_local(points[box == b], boxes, b) for b in np.unique(box[~static])}
    origin = k.ego_pose[:3, :3] @ k.lidar_to_ego[:3, 3] + k.ego_pose[:3, 3]
    return SweepPoints(origin, world, labels[static], carried)


@dataclass(frozen=True)
class KeyframePoints:
    """Aggregated points in a keyframe's ego frame; `origin` (N, 3): the LiDAR centre each point's ray came from,
    NaN for a carried box point of another sweep (its ray crossed space as it was then, not at the keyframe)."""

    points: np.ndarray
    labels: np.ndarray
    origin: np.ndarray


def keyframe_points(drive: NuScenesDrive, sweeps: dict[int, SweepPoints], index: int) -> KeyframePoints:
    """The chosen sweeps' points in keyframe `index`'s ego frame (boxes and pose of that keyframe)."""
    world_to_ego = np.linalg.inv(drive[index].ego_pose)
    r, t = world_to_ego[:3, :3], world_to_ego[:3, 3]
    boxes = boxes_in_frame(drive.boxes(index), world_to_ego)
    slot = {token: b for b, token in enumerate(boxes.instances)}
    points, labels, origins = [], [], []
    for j, sweep in sweeps.items():
        origin = r @ sweep.origin + t
        points.append(sweep.static @ r.T + t)
        labels.append(sweep.static_labels)
        origins.append(np.broadcast_to(origin, sweep.static.shape))
        for token, local in sweep.in_box.items():
            b = slot.get(token)
            if b is None:
                continue  # the instance has no box at this keyframe: its points go with it
            points.append(local @ boxes.rotations[b].T + boxes.centres[b])
            labels.append(np.full(len(local), boxes.labels[b], np.uint8))
            origins.append(np.broadcast_to(origin if j == index else np.nan, local.shape))
    return KeyframePoints(np.concatenate(points), np.concatenate(labels), np.concatenate(origins))
