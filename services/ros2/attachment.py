"""rmw_zenoh's attachment on every sample: zenoh-ext serialisation of (int64 sequence number, int64 source timestamp
in ns, 16-byte gid as a sequence: its length as LEB128, one byte, then the bytes), little-endian, 33 bytes."""

from __future__ import annotations

import struct
from dataclasses import dataclass

GID_SIZE = 16
_FORMAT = struct.Struct(f"<qqB{GID_SIZE}s")


@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes

    def encode(self) -> bytes:
        return _FORMAT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE, self.source_gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        if len(data) != _FORMAT.size:
            raise ValueError(f"an rmw_zenoh attachment has {_FORMAT.size} bytes, this one {len(data)}")
        seq, stamp, n, g = _FORMAT.unpack(data)
        if n != GID_SIZE:
            raise ValueError(f"attachment gid of {n} bytes, not {GID_SIZE}")
        return cls(seq, stamp, g)
