"""The evicted map, in either database: the tiles a stream's working set let go (written by the frame log's
finish_frame), read back when the vehicle returns or a resume needs the map as it was after a frame."""

from __future__ import annotations


class ColdTiles:
    def __init__(self, db):
        self.db = db

    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]:
        """{(ix, iy): [evicted_seq, ...]} of the tiles out of the working set: now, or just after frame as_of_seq.
        (One block a tile, unless a frame reached into a tile already evicted.)"""
        if as_of_seq is None:
            rows = self.db.read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream = ? AND restored_seq IS NULL", (stream,)
            )
        else:
            rows = self.db.read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream = ? AND evicted_seq <= ? "
                "AND (restored_seq IS NULL OR restored_seq > ?)",
                (stream, as_of_seq, as_of_seq),
            )
        out: dict[tuple[int, int], list[int]] = {}
        for ix, iy, e in sorted(rows):
            out.setdefault((int(ix), int(iy)), []).append(int(e))
        return out

    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes:
        rows = self.db.read(
            "SELECT block FROM cold_tiles WHERE stream = ? AND ix = ? AND iy = ? AND evicted_seq = ?",
            (stream, ix, iy, evicted_seq),
            True,
        )
        if not rows:
            raise KeyError(f"stream {stream}: no cold tile {ix},{iy} evicted at seq {evicted_seq}")
        return rows[0][0]
