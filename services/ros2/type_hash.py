"""RIHS01 type hashes (REP-2011) computed from message definitions: the hash rmw_zenoh puts in every key expression
and liveliness token, so a subscriber only matches a publisher of the same definition."""

from __future__ import annotations

import hashlib
import json

from rosbags.typesys.store import Typestore

# rosidl's type_description_interfaces FieldType ids
BASE_IDS = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "char": 3,  # a .msg char is a uint8
    "bool": 15,
    "byte": 16,
    "string": 17,
    "wstring": 18,
}
NESTED, BOUNDED_STRING, BOUNDED_WSTRING = 1, 21, 22
ARRAY, BOUNDED_SEQUENCE, SEQUENCE = 48, 96, 144  # offsets added to the element's id


def _element(desc) -> tuple[int, int, str]:
    """(type id, string capacity, nested type name) of a field's element."""
    kind, arg = desc
    if kind.name == "NAME":
        return NESTED, 0, arg
    name, bound = arg
    if bound and name in ("string", "wstring"):
        return (BOUNDED_STRING if name == "string" else BOUNDED_WSTRING), bound, ""
    return BASE_IDS[name], 0, ""


def _field_type(desc) -> dict:
    kind, arg = desc
    offset, capacity = 0, 0
    if kind.name in ("ARRAY", "SEQUENCE"):
        desc, capacity = arg
        offset = ARRAY if kind.name == "ARRAY" else (BOUNDED_SEQUENCE if capacity else SEQUENCE)
    type_id, string_capacity, nested = _element(desc)
    return {
        "type_id": type_id + offset,
        "capacity": capacity,
        "string_capacity": string_capacity,
        "nested_type_name": nested,
    }


def _individual(store: Typestore, name: str) -> tuple[dict, set[str]]:
    fields, nested = [], set()
    for fname, desc in store.fielddefs[name][1]:
        ftype = _field_type(desc)
        fields.append({"name": fname, "type": ftype})
        if ftype["nested_type_name"]:
            nested.add(ftype["nested_type_name"])
    if not fields:  # rosidl gives an empty message one placeholder member
        placeholder = {"type_id": BASE_IDS["uint8"], "capacity": 0, "string_capacity": 0, "nested_type_name": ""}
        fields.append({"name": "structure_needs_at_least_one_member", "type": placeholder})
    return {"type_name": name, "fields": fields}, nested


def type_description(store: Typestore, name: str) -> dict:
    """The hashed form of a type: its fields, and every type it refers to (sorted by name); no default values."""
    main, todo = _individual(store, name)
    refs: dict[str, dict] = {}
    while todo:
        ref = todo.pop()
        if ref in refs:
            continue
        refs[ref], more = _individual(store, ref)
        todo |= more - refs.keys()
    return {"type_description": main, "referenced_type_descriptions": [refs[k] for k in sorted(refs)]}


def rihs01(store: Typestore, name: str) -> str:
    """`RIHS01_<sha256 hex>` of the type description as rosidl serialises it (JSON, ', ' and ': ' separators)."""
    text = json.dumps(type_description(store, name), separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()
