"""The Zenoh encoding of every occvo put and reply: application/msgpack with the message's schema (kind and version,
the $id of its JSON Schema), so a reader in any language knows what a sample holds before decoding it."""

from __future__ import annotations

import functools

import zenoh

from occvo_schemas.codec import MEDIA_TYPE, schema_id


@functools.cache
def encoding(kind: str, version: int | None = None) -> zenoh.Encoding:
    """e.g. encoding("pose_estimate"): application/msgpack;occvo/pose_estimate/v2 (the kind's newest version
    unless told)"""
    return zenoh.Encoding(f"{MEDIA_TYPE};{schema_id(kind, version)}")


def blocking(kind: str, version: int | None = None) -> dict:
    """A put's keywords: its encoding, and block rather than drop (every occvo put is a message someone waits for)."""
    return {"encoding": encoding(kind, version), "congestion_control": zenoh.CongestionControl.BLOCK}


# what each published key carries (schemas/keys.py; docs/service.md's key table): one kind and version a key
_KIND_OF_KEY_END = {
    "/camera": ("camera_frame", None),
    "/occupancy": ("occupancy_frame", None),
    "/pose/v2": ("pose_estimate", 2),
    "/pose": ("pose_estimate", 1),  # for clients built before version 2 (schemas/pose_v1.py)
    "/map/updates": ("map_update", None),
    "/errors": ("error_event", None),
}


def blocking_at(key: str) -> dict:
    """blocking(kind) for a put on one of the published keys (occvo/<stream>/pose/v2, .../map/updates, ...)."""
    for end, (kind, version) in _KIND_OF_KEY_END.items():
        if key.endswith(end):
            return blocking(kind, version)
    raise ValueError(f"{key} is not a key occvo publishes on")
