"""Map quality as in the paper's Table IV: accuracy, precision and completion ratio of a reconstructed map.

    accuracy    RMSE (m) of the distance from each reconstructed point to its nearest ground-truth point
    precision   share of reconstructed points within `threshold` (0.4 m) of a ground-truth point
    completion  share of ground-truth points within `threshold` of a reconstructed point

"Within" is inclusive (d <= threshold). By default both maps keep only the static classes
(occvo_core.grid.STATIC_CLASSES), the paper's setting. A synthetic scene has a true static map; a recorded
one does not, and `reference_map_from_poses` builds a stand-in, labelled as such (MapCloud.kind).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from occvo_core.errors import DatasetError
from occvo_core.eval import umeyama_se3
from occvo_core.grid import STATIC_CLASSES

THRESHOLD_M = 0.4
TRUE_MAP = "true static map (synthetic ground truth)"
REFERENCE_MAP = "reference map: the scene's own occupancy accumulated along ground-truth poses (not ground truth)"


@dataclass
class MapCloud:
    """A labelled map: points (M,3) world, labels (M,) uint8 or None, and what it is. Unpacks as (points, labels)."""

    points: np.ndarray
    labels: np.ndarray | None
    kind: str = ""

    def __iter__(self):
        return iter((self.points, self.labels))

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class MapMetrics:
    accuracy: float  # m, RMSE of reconstructed -> ground-truth distances
    precision: float  # 0..1
    completion: float  # 0..1
    n_reconstructed: int  # points compared after class filtering
    n_ground_truth: int
    threshold: float = THRESHOLD_M
    reference: str = ""  # what the ground-truth map was

    def as_dict(self) -> dict:
        return {
            "accuracy": self.accuracy,
            "precision": self.precision,
            "completion": self.completion,
            "n_reconstructed": self.n_reconstructed,
            "n_ground_truth": self.n_ground_truth,
            "threshold_m": self.threshold,
            "reference": self.reference,
        }


def _select(points, labels, classes) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if classes is None or labels is None:
        return points
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(points):
        raise ValueError(f"{len(points)} points but {len(labels)} labels")
    return points[np.isin(labels, np.asarray(classes))]


def map_metrics(
    est_points: np.ndarray,
    est_labels: np.ndarray | None,
    gt_points: np.ndarray,
    gt_labels: np.ndarray | None,
    threshold: float = THRESHOLD_M,
    classes=STATIC_CLASSES,
    reference: str = "",
) -> MapMetrics:
    """Compare a reconstructed map with a ground-truth map in the same frame. classes=None keeps every point;
    a map without labels is compared whole. Empty maps give NaN accuracy and zero precision / completion."""
    est = _select(est_points, est_labels, classes)
    gt = _select(gt_points, gt_labels, classes)
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(gt))):
        raise ValueError("map points must be finite")
    if len(est) == 0 or len(gt) == 0:
        return MapMetrics(float("nan"), 0.0, 0.0, len(est), len(gt), threshold, reference)
    d_est, _ = cKDTree(gt).query(est, k=1)
    d_gt, _ = cKDTree(est).query(gt, k=1)
    tol = threshold + 1e-9
    return MapMetrics(
        float(np.sqrt(np.mean(d_est**2))),
        float(np.mean(d_est <= tol)),
        float(np.mean(d_gt <= tol)),
        len(est),
        len(gt),
        threshold,
        reference,
    )


def voxel_downsample(
    points: np.ndarray, labels: np.ndarray | None, voxel: float = 0.4
) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per world voxel (its centre); the label most often seen in that voxel (ties: lowest class id)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return points, (None if labels is None else np.zeros(0, np.uint8))
    keys = np.floor(points / voxel).astype(np.int64)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    centres = (uniq + 0.5) * voxel
    if labels is None:
        return centres, None
    counts = np.zeros((len(uniq), 256), np.int64)
    np.add.at(counts, (inverse, np.asarray(labels, dtype=np.int64)), 1)
    return centres, counts.argmax(axis=1).astype(np.uint8)


def reference_map_from_poses(
    source, poses: np.ndarray | None = None, voxel: float = 0.4, classes=STATIC_CLASSES
) -> MapCloud:
    """Stand-in map for scenes with no true map: every frame's occupied voxels of `classes`, moved to the world
    by the ground-truth poses (source.gt_poses unless given) and voxel-downsampled. It inherits the occupancy's
    errors, so metrics against it measure consistency with the scene's own predictions, not truth."""
    poses = source.gt_poses if poses is None else np.asarray(poses)
    if poses is None:
        raise DatasetError(getattr(source, "name", source), "no ground-truth poses to build a reference map from")
    if len(poses) < len(source):
        raise DatasetError(getattr(source, "name", source), f"{len(poses)} poses for {len(source)} frames")
    pts, labs = [], []
    for i in range(len(source)):
        frame = source[i]
        keep = np.ones(len(frame.labels), bool) if classes is None else np.isin(frame.labels, np.asarray(classes))
        pts.append(frame.points[keep] @ poses[i][:3, :3].T + poses[i][:3, 3])
        labs.append(frame.labels[keep])
    points, labels = voxel_downsample(np.concatenate(pts), np.concatenate(labs), voxel)
    return MapCloud(points, labels, REFERENCE_MAP)


def ground_truth_map(source) -> MapCloud:
    """The scene's true static map if it has one (synthetic scenes), else the labelled reference map."""
    if hasattr(source, "static_map"):
        points, labels = source.static_map()
        return MapCloud(points, labels, TRUE_MAP)
    return reference_map_from_poses(source)


def align_to_ground_truth(
    points: np.ndarray, est_poses: np.ndarray, gt_poses: np.ndarray, lever_m: float = 10.0
) -> np.ndarray:
    """Map points from the estimate's world frame to the ground truth's by an SE(3) Umeyama fit over the poses:
    each pose contributes its position and the tips of its three axes `lever_m` long. Orientation makes the fit
    well posed on straight drives, where positions alone (APE's alignment) leave the roll about the road free."""
    est_poses, gt_poses = np.asarray(est_poses, np.float64), np.asarray(gt_poses, np.float64)
    if est_poses.shape != gt_poses.shape or len(est_poses) == 0:
        raise ValueError(f"need matching (N,4,4) trajectories, got {est_poses.shape} and {gt_poses.shape}")

    def anchors(poses):
        tips = poses[:, :3, 3][:, None, :] + lever_m * poses[:, :3, :3].transpose(0, 2, 1)
        return np.concatenate([poses[:, :3, 3], tips.reshape(-1, 3)])

    rot, trans = umeyama_se3(anchors(est_poses), anchors(gt_poses))
    return np.asarray(points, dtype=np.float64) @ rot.T + trans


def evaluate_map_against_truth(source, odometry, threshold: float = THRESHOLD_M, classes=STATIC_CLASSES) -> dict:
    """Map metrics of an OccVO run (after its last frame) against the scene's true or reference map.

    `odometry` needs .poses (T,4,4), .frame_indices and .map_points(); the estimate is aligned to the ground
    truth as for APE. Returns MapMetrics.as_dict(), whose "reference" says which map was the truth."""
    gt_poses = source.gt_poses
    if gt_poses is None:
        raise DatasetError(getattr(source, "name", source), "map metrics need ground-truth poses")
    indices = list(getattr(odometry, "frame_indices", range(len(odometry.poses))))
    est_points, est_labels = odometry.map_points()
    aligned = align_to_ground_truth(est_points, odometry.poses, gt_poses[indices])
    truth = ground_truth_map(source)
    return map_metrics(aligned, est_labels, truth.points, truth.labels, threshold, classes, truth.kind).as_dict()


# -- map files: .npz (points, labels) or .ply (x, y, z and optionally label / class / semantic) ----------------


def load_map(path: str | Path) -> MapCloud:
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "map file does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "points" not in z:
                    raise DatasetError(path, f"npz map needs a 'points' array, found {sorted(z.files)}")
                points = np.asarray(z["points"], dtype=np.float64)
                labels = np.asarray(z["labels"]) if "labels" in z else None
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(path, f"unreadable npz map: {exc}") from None
    elif suffix == ".ply":
        points, labels = _read_ply(path)
    else:
        raise DatasetError(path, "map files are .npz (points, labels) or .ply")
    if points.ndim != 2 or points.shape[1] != 3:
        raise DatasetError(path, f"points must be (M, 3), got {points.shape}")
    if labels is not None and labels.shape != (len(points),):
        raise DatasetError(path, f"labels must be ({len(points)},), got {labels.shape}")
    if not np.all(np.isfinite(points)):
        raise DatasetError(path, "map has non-finite coordinates")
    return MapCloud(points, None if labels is None else labels.astype(np.uint8), str(path))


def save_map(path: str | Path, points: np.ndarray, labels: np.ndarray | None = None) -> None:
    """.npz with points and labels, or binary .ply with x, y, z (float64) and label (uchar)."""
    path = Path(path)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if path.suffix.lower() == ".ply":
        fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")] + ([("label", "u1")] if labels is not None else [])
        rec = np.empty(len(points), dtype=fields)
        rec["x"], rec["y"], rec["z"] = points.T
        if labels is not None:
            rec["label"] = labels
        props = "".join(f"property {'double' if t == '<f8' else 'uchar'} {n}\n" for n, t in fields)
        header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n{props}end_header\n"
        path.write_bytes(header.encode() + rec.tobytes())
    else:
        arrays = {"points": points} if labels is None else {"points": points, "labels": np.asarray(labels, np.uint8)}
        np.savez_compressed(path, **arrays)


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_LABEL_NAMES = ("label", "class", "semantic", "semantics", "scalar_label")


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(path, "not a PLY file (no 'ply' magic or end_header)")
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[end + len(b"end_header") :]
    body = body[1:] if body[:1] == b"\n" else body[2:] if body[:2] == b"\r\n" else body
    fmt, count, props, in_vertex = None, 0, [], False
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                count = int(parts[2])
            elif count and not props:
                raise DatasetError(path, "PLY vertex element must come first")
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list":
                raise DatasetError(path, "PLY vertex list properties are not supported")
            if parts[1] not in _PLY_TYPES:
                raise DatasetError(path, f"unknown PLY property type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(path, f"PLY vertices need x, y, z properties, found {names}")
    try:
        if fmt == "ascii":
            rows = np.loadtxt(body.decode("ascii").splitlines()[:count], ndmin=2)
            rec = {n: rows[:, i] for i, n in enumerate(names)}
        elif fmt in ("binary_little_endian", "binary_big_endian"):
            order = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(n, order + t) for n, t in props])
            rec = np.frombuffer(body, dtype=dt, count=count)
        else:
            raise DatasetError(path, f"unsupported PLY format {fmt!r}")
    except ValueError as exc:
        raise DatasetError(path, f"truncated or malformed PLY body: {exc}") from None
    points = np.column_stack([np.asarray(rec[a], dtype=np.float64) for a in "xyz"])
    label_name = next((n for n in _LABEL_NAMES if n in names), None)
    labels = None if label_name is None else np.asarray(rec[label_name]).astype(np.int64)
    if labels is not None and labels.size and (labels.min() < 0 or labels.max() > 255):
        raise DatasetError(path, f"labels outside 0..255 in property {label_name!r}")
    return points, labels
