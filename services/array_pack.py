"""Numpy arrays as one flat blob, what the stores keep (journal frames, cold tiles, snapshots): a JSON header of names,
dtypes, shapes and offsets, then each array's bytes at a 64-byte boundary. Its size is known before a byte is written
and it is written in one pass, each array from its own memory; np.savez wrote a snapshot twice (a pass to size the
row), copying and CRC-ing every array through zipfile. Blobs written as .npz before are still read."""

from __future__ import annotations

import io
import json
import struct

import numpy as np

MAGIC = b"OVA1"
ALIGN = 64


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def layout(arrays: dict[str, np.ndarray]) -> tuple[bytes, list[np.ndarray], int]:
    """(header padded to ALIGN, the arrays as C-contiguous ones, total size in bytes)."""
    meta, items, offset = [], [], 0
    for name, a in arrays.items():
        a = np.asarray(a)
        a = a if a.flags.c_contiguous else a.copy(order="C")  # (ascontiguousarray makes 0-d arrays 1-d)
        if a.dtype.hasobject or a.dtype.fields is not None:
            raise TypeError(f"array {name!r}: dtype {a.dtype} cannot be packed (plain numbers only)")
        meta.append({"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "offset": offset})
        items.append(a)
        offset += _aligned(a.nbytes)
    header = json.dumps(meta, separators=(",", ":")).encode()
    head = MAGIC + struct.pack("<I", len(header)) + header
    return head.ljust(_aligned(len(head)), b"\0"), items, _aligned(len(head)) + offset


def chunks(head: bytes, items: list[np.ndarray]):
    """layout()'s blob piece by piece, each array as a view of its own memory."""
    yield head
    for a in items:
        yield a.reshape(-1).view(np.uint8).data
        yield b"\0" * (_aligned(a.nbytes) - a.nbytes)


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """numpy arrays -> one blob (no pickle, no compression: the blobs are read back whole and soon)."""
    head, items, _ = layout(arrays)
    return b"".join(chunks(head, items))


def unpack_arrays(blob) -> dict[str, np.ndarray]:
    """pack_arrays' blob (or an .npz of a store written before) -> writable arrays of their own."""
    view = memoryview(blob)
    if bytes(view[:4]) != MAGIC:
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    try:
        (n,) = struct.unpack_from("<I", view, 4)
        start = _aligned(8 + n)
        out = {}
        for m in json.loads(bytes(view[8 : 8 + n])):
            dtype, shape = np.dtype(m["dtype"]), tuple(m["shape"])
            count = int(np.prod(shape, dtype=np.int64))
            flat = np.frombuffer(view, dtype, count, start + m["offset"]) if count else np.empty(0, dtype)
            out[m["name"]] = flat.reshape(shape).copy()
    except (struct.error, ValueError, KeyError, TypeError) as exc:  # a cut or damaged blob
        raise ValueError(f"packed arrays unreadable ({len(view)} bytes): {exc}") from None
    return out
