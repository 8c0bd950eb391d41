"""Writing results: coloured PLY maps, map archives and the top-view trajectory plot."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from occvo_core.grid import CLASS_COLORS, CLASS_NAMES


def write_text_atomic(path: str | Path, text: str) -> None:
    """The whole text or nothing at path: written under a temporary name beside it, then renamed."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_ply(path: str | Path, points: np.ndarray, labels: np.ndarray) -> None:
    """Binary PLY with x, y, z, the class colour and the class label, readable by open3d, CloudCompare, MeshLab."""
    labels = np.asarray(labels, np.uint8)
    rows = np.empty(
        len(points),
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("label", "u1"),
        ],
    )
    rows["x"], rows["y"], rows["z"] = np.asarray(points, np.float32).T
    rgb = CLASS_COLORS[labels]
    rows["red"], rows["green"], rows["blue"] = rgb.T
    rows["label"] = labels
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment classes: {' '.join(f'{i}={n}' for i, n in enumerate(CLASS_NAMES))}\n"
        f"element vertex {len(rows)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar label\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rows.tobytes())


def read_map(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, labels) from a map.npz or a PLY; labels are 255 where the file has none."""
    from occvo_core.map_metrics import load_map

    cloud = load_map(path)
    labels = cloud.labels if cloud.labels is not None else np.full(len(cloud.points), 255, np.uint8)
    return cloud.points, labels


def plot_trajectory(path: str | Path, est: np.ndarray, gt: np.ndarray | None = None, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from occvo_core.eval import umeyama_se3

    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    p = est[:, :3, 3]
    if gt is not None:
        g = gt[:, :3, 3]
        rot, trans = umeyama_se3(p, g)
        p = p @ rot.T + trans
        ax.plot(g[:, 0], g[:, 1], "-", color="0.4", lw=2, label="ground truth")
    ax.plot(
        p[:, 0],
        p[:, 1],
        "-o",
        color="tab:red",
        ms=2,
        lw=1,
        label="OCC-VO estimate" + (" (aligned)" if gt is not None else ""),
    )
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
