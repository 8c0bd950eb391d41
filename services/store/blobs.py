"""What the stores keep as blobs: the journal's frames (numpy arrays packed by services/array_pack.py), and the digest
that identifies a frame for idempotent resends."""

from __future__ import annotations

import hashlib

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID
from occvo_core.grid_kernels import used_cells
from occvo_services.array_pack import pack_arrays, unpack_arrays


def frame_digest(
    points: np.ndarray, labels: np.ndarray, stamp: float, tables: tuple[np.ndarray, np.ndarray | None] | None = None
) -> bytes:
    """What identifies a frame for idempotent resends: its stamp and its exact content. A frame on the Occ3D grid is
    hashed in its compact form (its indices and the coordinates of the indices in use: GridSpec.axis_tables), 3 bytes
    a voxel instead of 24; `tables`: that form as it arrived (indices, axes or None for the centres), else derived
    from the points. Either way the same points give the same digest."""
    used = None if tables is None else _used(*tables)
    if used is None:
        tables = OCC3D_GRID.axis_tables(points)
        used = None if tables is None else _used(*tables)
    h = hashlib.blake2b(np.float64(stamp).tobytes(), digest_size=16)
    if used is None:
        h.update(b"points")
        h.update(np.ascontiguousarray(points, np.float64).tobytes())
    else:
        idx, axes = tables
        axes = OCC3D_GRID.centre_table() if axes is None else axes
        h.update(b"grid")
        h.update(np.ascontiguousarray(idx, np.uint8).tobytes())
        for a in range(3):
            h.update(np.packbits(used[a]).tobytes())
            h.update(np.ascontiguousarray(axes[a, used[a]], np.float64).tobytes())
    h.update(np.ascontiguousarray(labels, np.uint8).tobytes())
    return h.digest()


def _used(idx: np.ndarray, axes: np.ndarray | None) -> list[np.ndarray] | None:
    """Per axis, the grid indices in use; None unless they are the ones axis_tables gives for the points they
    describe (each coordinate in use lies in its own voxel: a sender may name any index for a coordinate)."""
    n = max(OCC3D_GRID.shape)
    if len(idx) and int(idx.max()) >= n:
        return None
    used = list(used_cells(idx, n))
    if axes is None or len(idx) == 0:
        return used
    for a in range(3):
        at = np.flatnonzero(used[a])
        if not np.array_equal(OCC3D_GRID.axis_indices(a, axes[a, at]), at):
            return None
    return used


def legacy_frame_digest(points: np.ndarray, labels: np.ndarray, stamp: float) -> bytes:
    """The digest of stores written before the compact one: a resend of a frame they registered is still known."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.float64(stamp).tobytes())
    h.update(np.ascontiguousarray(points, np.float64).tobytes())
    h.update(np.ascontiguousarray(labels, np.uint8).tobytes())
    return h.digest()


def pack_frame(frame: OccupancyFrame, tables: tuple[np.ndarray, np.ndarray | None] | None = None) -> bytes:
    """A journal entry. Frames on the Occ3D grid are kept as uint8 indices, 3 bytes a voxel instead of 24, with the
    grid's per-axis coordinates where they are not the nominal centres (recorded frames: GridSpec.axis_tables): the
    journal is most of what the store writes, and its WAL checkpoints held every stream's commit. Exact: the same
    coordinates come back bit for bit. `tables`: the frame's Occ3D indices and axes (None: the centres) as it
    arrived, kept as they are instead of derived again from its points (a cost on every commit)."""
    head = {"labels": frame.labels, "index": np.int64(frame.index), "stamp": np.float64(frame.stamp)}
    if tables is None:
        points = np.asarray(frame.points, np.float64)
        tables = OCC3D_GRID.axis_tables(points)
        if tables is None:
            return pack_arrays({"points": points, **head})
    ijk, axes = tables
    if axes is None or np.array_equal(axes, OCC3D_GRID.centre_table()):  # voxel centres: the grid gives them back
        return pack_arrays({"ijk": ijk.astype(np.uint8), **head})
    return pack_arrays({"ijk": ijk.astype(np.uint8), "axes": axes, **head})


def unpack_frame(blob: bytes) -> OccupancyFrame:
    a = unpack_arrays(blob)
    if "ijk" not in a:
        points = a["points"]
    elif "axes" in a:
        points = OCC3D_GRID.points_of(a["ijk"].astype(np.int64), a["axes"])
    else:
        points = OCC3D_GRID.centres_of(a["ijk"].astype(np.int64))
    return OccupancyFrame(points, a["labels"], index=int(a["index"]), stamp=float(a["stamp"]))
