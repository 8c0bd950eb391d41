"""msgpack codec for the messages in occvo_schemas.models: arrays as raw bytes, a size limit, kind and version checks.

Every failure is a CodecError whose `code` is an ErrorEvent code and whose message names the problem.
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from occvo_schemas.models import MESSAGES, VERSIONS

DEFAULT_MAX_BYTES = 16 * 1024 * 1024  # 6 JPEG images or a 640k-voxel frame fit with room to spare
# Decode limits, checked by msgpack before it builds anything: no message has long strings, long lists or big maps
# (arrays travel as bin). A 13.7 MB payload of 1.9M two-key maps took 5.3 s to unpack without them.
MAX_STR_LEN = 64 * 1024
MAX_ARRAY_LEN = 65536  # MapInfo.tiles, WorkerHealth.streams
MAX_MAP_LEN = 4096  # timings_ms, counters
MAX_ELEMENTS = 1 << 16  # all lists' and maps' entries together: many short containers cost as much as one long one
# (MapInfo of a 10 km drive: ~20k); 2^18 let a 16 MB payload of small maps cost 70 to 90 ms before its refusal
# nesting: msgpack's own stack stops at 1024 levels (StackError, reported as malformed)
T = TypeVar("T", bound=BaseModel)


def schema_id(kind: str, version: int | None = None) -> str:
    """The name of a message's schema (its newest version unless told): the $id of schemas/json/<kind>.json and,
    after "application/msgpack;", the Zenoh encoding every put and reply of it carries."""
    return f"occvo/{kind}/v{VERSIONS[kind] if version is None else version}"


MEDIA_TYPE = "application/msgpack"


class CodecError(ValueError):
    def __init__(self, code: str, message: str):
        self.code = code
        self.message = message
        super().__init__(f"{code}: {message}")


def encode(message: BaseModel, max_bytes: int = DEFAULT_MAX_BYTES) -> bytes:
    try:
        data = msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)
    except (OverflowError, TypeError, ValueError) as exc:  # e.g. an int beyond msgpack's 64 bits
        raise CodecError(
            "invalid_message", f"{getattr(message, 'kind', type(message).__name__)} cannot be encoded: {exc}"
        ) from None
    if len(data) > max_bytes:
        raise CodecError("oversize", f"{message.kind} of {len(data)} bytes exceeds the limit of {max_bytes}")
    return data


def _summary(exc: ValidationError) -> str:
    parts = []
    for e in exc.errors()[:3]:
        where = ".".join(str(p) for p in e["loc"]) or "message"
        parts.append(f"{where}: {e['msg']}")
    more = f" (+{exc.error_count() - 3} more)" if exc.error_count() > 3 else ""
    return "; ".join(parts) + more


def _unpack(data: bytes, max_bytes: int):
    left = [MAX_ELEMENTS]

    def count(container):  # called as each list or map is complete: stops a message of many small ones early
        left[0] -= len(container) + 1
        if left[0] < 0:
            raise CodecError("malformed", f"more than {MAX_ELEMENTS} list and map entries in one message")
        return container

    return msgpack.unpackb(
        data,
        raw=False,
        strict_map_key=True,
        max_str_len=MAX_STR_LEN,
        max_bin_len=max_bytes,
        max_array_len=MAX_ARRAY_LEN,
        max_map_len=MAX_MAP_LEN,
        max_ext_len=0,
        list_hook=count,
        object_hook=count,
    )


def decode(
    data: bytes,
    expect: type[T] | tuple[type, ...] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    context: dict | None = None,
) -> T:
    """bytes -> a validated message; `expect` restricts which models are accepted; `context` goes to the validators
    (models.SHAPES_ONLY: an occupancy's arrays checked for their shapes only)."""
    if len(data) > max_bytes:
        raise CodecError("oversize", f"payload of {len(data)} bytes exceeds the limit of {max_bytes}")
    try:
        obj = _unpack(data, max_bytes)
    except CodecError:
        raise
    except msgpack.StackError:
        raise CodecError("malformed", "not a msgpack message: nested deeper than 1024 levels") from None
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types on garbage
        raise CodecError("malformed", f"not a msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, dict):
        raise CodecError("malformed", f"a message is a msgpack map, got {type(obj).__name__}")
    kind = obj.get("kind")
    model = MESSAGES.get(kind) if isinstance(kind, str) else None
    if model is None:
        raise CodecError("unknown_kind", f"unknown message kind {kind!r}; known: {sorted(MESSAGES)}")
    version = obj.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise CodecError("unsupported_version", f"{kind}: schema_version missing or not an integer ({version!r})")
    if version > VERSIONS[kind]:
        raise CodecError(
            "unsupported_version", f"{kind}: schema_version {version} is newer than this build's {VERSIONS[kind]}"
        )
    if version < 1:
        raise CodecError("unsupported_version", f"{kind}: schema_version {version} is not a valid version")
    if expect is not None:
        allowed = expect if isinstance(expect, tuple) else (expect,)
        if model not in allowed:
            names = [m.model_fields["kind"].default for m in allowed]
            raise CodecError("unknown_kind", f"expected {' or '.join(names)}, got {kind}")
    try:
        return model.model_validate(obj, context=context)
    except ValidationError as exc:
        raise CodecError("invalid_message", f"{kind}: {_summary(exc)}") from None
    except Exception as exc:  # noqa: BLE001 - a validator failing otherwise (OverflowError...) is still a bad message
        raise CodecError("invalid_message", f"{kind}: {type(exc).__name__}: {exc}") from None
