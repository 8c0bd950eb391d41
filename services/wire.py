"""The Zenoh encoding of every occvo put and reply: application/msgpack with the message's schema (kind and version,
the $id of its JSON Schema), so a reader in any language knows what a sample holds before decoding it."""

from __future__ import annotations

import functools

import zenoh

from occvo_schemas.codec import MEDIA_TYPE, schema_id


@functools.cache
def encoding(kind: str) -> zenoh.Encoding:
    """e.g. encoding("pose_estimate"): application/msgpack;occvo/pose_estimate/v1"""
    return zenoh.Encoding(f"{MEDIA_TYPE};{schema_id(kind)}")


def blocking(kind: str) -> dict:
    """A put's keywords: its encoding, and block rather than drop (every occvo put is a message someone waits for)."""
    return {"encoding": encoding(kind), "congestion_control": zenoh.CongestionControl.BLOCK}


# what each published key carries (schemas/keys.py; docs/service.md's key table): one kind a key
_KIND_OF_KEY_END = {
    "/camera": "camera_frame",
    "/occupancy": "occupancy_frame",
    "/pose": "pose_estimate",
    "/map/updates": "map_update",
    "/errors": "error_event",
}


def blocking_at(key: str) -> dict:
    """blocking(kind) for a put on one of the published keys (occvo/<stream>/pose, .../map/updates, ...)."""
    for end, kind in _KIND_OF_KEY_END.items():
        if key.endswith(end):
            return blocking(kind)
    raise ValueError(f"{key} is not a key occvo publishes on")
