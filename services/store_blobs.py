"""What the stores keep as blobs: numpy arrays as .npz bytes (written in place into a SQLite blob when large), the
journal's frames, and the digest that identifies a frame for idempotent resends."""

from __future__ import annotations

import hashlib
import io

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """numpy arrays -> .npz bytes (no pickle, no compression: the blobs are read back whole and soon)."""
    buf = io.BytesIO()
    savez(buf, arrays)
    return buf.getvalue()


class BlobFile(io.RawIOBase):
    """A seekable file over a fixed-size SQLite blob, for np.savez to write into; with blob=None it only measures
    how many bytes would be written. The same arrays give the same bytes, so a measuring pass sizes the blob."""

    def __init__(self, blob=None):
        super().__init__()
        self.blob, self.pos, self.size = blob, 0, 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self.pos = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence] + offset
        return self.pos

    def write(self, data) -> int:
        n = memoryview(data).nbytes
        if self.blob is not None:
            self.blob.seek(self.pos)
            self.blob.write(data)
        self.pos += n
        self.size = max(self.size, self.pos)
        return n


def savez(fp, arrays: dict[str, np.ndarray]) -> None:
    np.savez(fp, **{k: np.asarray(v) for k, v in arrays.items()})


def unpack_arrays(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def frame_digest(points: np.ndarray, labels: np.ndarray, stamp: float) -> bytes:
    """What identifies a frame for idempotent resends: its stamp and its exact content."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.float64(stamp).tobytes())
    h.update(np.ascontiguousarray(points, np.float64).tobytes())
    h.update(np.ascontiguousarray(labels, np.uint8).tobytes())
    return h.digest()


def pack_frame(frame: OccupancyFrame) -> bytes:
    """A journal entry. Frames on the Occ3D grid are kept as uint8 indices, 3 bytes a voxel instead of 24, with the
    grid's per-axis coordinates where they are not the nominal centres (recorded frames: GridSpec.axis_tables): the
    journal is most of what the store writes, and its WAL checkpoints held every stream's commit. Exact: the same
    coordinates come back bit for bit."""
    head = {"labels": frame.labels, "index": np.int64(frame.index), "stamp": np.float64(frame.stamp)}
    points = np.asarray(frame.points, np.float64)
    tables = OCC3D_GRID.axis_tables(points)
    if tables is None:
        return pack_arrays({"points": points, **head})
    ijk, axes = tables
    if np.array_equal(axes, OCC3D_GRID.centre_table()):  # voxel centres: the grid gives them back
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
