"""The stores' array blobs (services/array_pack.py): exact round trips, the .npz blobs of stores written before, and
damaged blobs refused."""

from __future__ import annotations

import io

import numpy as np
import pytest

from occvo_services.array_pack import pack_arrays, unpack_arrays

ARRAYS = {
    "points": np.arange(24.0).reshape(4, 6)[:, ::2],  # not contiguous
    "alive": np.array([True, False, True]),
    "empty": np.zeros((0, 17)),
    "index": np.int64(-7),
    "half": np.float16([1.5, -2.25]),
    "ijk": np.arange(9, dtype=np.uint8).reshape(3, 3),
    "counts": np.arange(6, dtype=">i4"),  # byte order kept
}


def test_arrays_come_back_bit_for_bit_and_writable():
    blob = pack_arrays(ARRAYS)
    assert pack_arrays(ARRAYS) == blob  # the same arrays give the same bytes
    back = unpack_arrays(blob)
    assert list(back) == list(ARRAYS)
    for name, a in ARRAYS.items():
        a = np.asarray(a)
        assert back[name].dtype == a.dtype and back[name].shape == a.shape, name
        assert back[name].tobytes() == a.tobytes(), name
    back["points"][0, 0] = 99.0  # their own memory: the blob is untouched
    assert unpack_arrays(blob)["points"][0, 0] == 0.0


def test_a_blob_of_a_store_written_before_is_read():
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in ARRAYS.items()})
    back = unpack_arrays(buf.getvalue())
    assert all(np.array_equal(back[k], np.asarray(v)) for k, v in ARRAYS.items())


def test_what_cannot_be_packed_or_read_is_refused_by_name():
    with pytest.raises(TypeError, match="'names'"):
        pack_arrays({"names": np.array(["a", None], dtype=object)})
    blob = pack_arrays(ARRAYS)
    with pytest.raises(ValueError, match="packed arrays unreadable"):
        unpack_arrays(blob[: len(blob) - 100])
    with pytest.raises(ValueError, match="packed arrays unreadable"):
        unpack_arrays(blob[:6])
