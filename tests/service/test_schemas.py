"""Wire models: validation of every message, JSON Schema files in sync with the models, key expressions."""

import json

import numpy as np
import pytest
from pydantic import ValidationError

from occvo_core.grid import OCC3D_GRID
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.export import JSON_DIR, drift, rendered
from occvo_schemas.models import (
    MESSAGES,
    SCHEMA_VERSION,
    VERSIONS,
    Array,
    CameraFrame,
    CameraImage,
    ErrorEvent,
    MapInfo,
    MapTile,
    MapUpdate,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
    WorkerHealth,
)


def test_json_schema_files_match_the_models():
    stale = drift()
    assert not stale, f"schemas/json drifted ({stale}); run python -m occvo_schemas.export"


def test_drift_check_notices_a_changed_file(tmp_path):
    for name, text in rendered().items():
        (tmp_path / name).write_text(text)
    assert drift(tmp_path) == []
    (tmp_path / "pose_estimate.json").write_text("{}")
    (tmp_path / "extra.json").write_text("{}")
    assert drift(tmp_path) == ["extra.json", "pose_estimate.json"]


def test_every_message_has_kind_version_and_a_schema_file():
    assert set(MESSAGES) == {p.stem for p in JSON_DIR.glob("*.json")}
    for kind, model in MESSAGES.items():
        assert model.model_fields["schema_version"].default == VERSIONS[kind] >= SCHEMA_VERSION
        schema = json.loads((JSON_DIR / f"{kind}.json").read_text())
        assert schema["$id"] == f"occvo/{kind}/v{VERSIONS[kind]}"
        assert "kind" in schema["properties"] and "schema_version" in schema["properties"]


def test_array_round_trip_and_size_check():
    a = np.arange(12, dtype=np.float64).reshape(4, 3)
    assert np.array_equal(Array.from_numpy(a).to_numpy(), a)
    with pytest.raises(ValidationError, match="needs 96 bytes"):
        Array(dtype="float64", shape=[4, 3], data=b"\0" * 95)
    with pytest.raises(ValueError, match="cannot travel"):
        Array.from_numpy(np.zeros(3, dtype=np.complex64))


def _occ(n=10, exact=True):
    rng = np.random.default_rng(0)
    idx = rng.integers(0, OCC3D_GRID.shape, size=(n, 3))
    return OCC3D_GRID.centres_of(idx), rng.integers(0, 17, n).astype(np.uint8)


@pytest.mark.parametrize("exact", [True, False])
def test_sparse_occupancy_both_encodings_give_the_points(exact):
    pts, labels = _occ()
    occ = SparseOccupancy.from_points(pts, labels, OCC3D_GRID, exact=exact)
    assert occ.points is None and occ.voxels.dtype == "uint8" and (occ.axes is not None) == exact
    np.testing.assert_array_equal(occ.to_points(), pts)
    assert len(occ) == 10


def test_recorded_coordinates_travel_as_indices_and_come_back_bit_for_bit():
    """The release's frames hold voxel centres to within rounding, one coordinate an index along each axis: they
    travel as 3 bytes a voxel plus the axes, and decode to the very same floats; points off that pattern travel as
    float64 coordinates."""
    pts, labels = _occ(500)
    idx = OCC3D_GRID.indices_of(pts)
    wobble = np.random.default_rng(1).integers(-3, 4, size=(3, 200)) * 2.0**-48  # per index, as the release's
    recorded = pts + np.stack([wobble[a, idx[:, a]] for a in range(3)], axis=1)
    assert not np.array_equal(recorded, pts)
    occ = SparseOccupancy.from_points(recorded, labels, OCC3D_GRID)
    assert occ.voxels is not None and occ.axes.shape == [3, 200]
    back = decode(encode(OccupancyFrameMsg(stream="s", seq=0, stamp=0.0, source="replay", occupancy=occ)))
    assert back.occupancy.to_points().tobytes() == recorded.tobytes()
    recorded[7, 0] += 1e-3  # now index idx[7, 0] holds two x coordinates
    occ = SparseOccupancy.from_points(recorded, labels, OCC3D_GRID)
    assert occ.voxels is None and occ.to_points().tobytes() == recorded.tobytes()


def test_sparse_occupancy_rejects_bad_axes():
    pts, labels = _occ()
    occ = SparseOccupancy.from_points(pts, labels, OCC3D_GRID)
    axes = occ.axes.to_numpy().copy()
    axes[2, 3] = np.nan
    with pytest.raises(ValidationError, match="axis 2 outside the grid or not finite"):
        SparseOccupancy(voxels=occ.voxels, axes=Array.from_numpy(axes), labels=occ.labels)
    with pytest.raises(ValidationError, match=r"axes must be \(3, 200\) float64"):
        SparseOccupancy(voxels=occ.voxels, axes=Array.from_numpy(axes[:, :16]), labels=occ.labels)
    with pytest.raises(ValidationError, match="axes come with voxels"):
        SparseOccupancy(points=Array.from_numpy(pts), axes=occ.axes, labels=occ.labels)


def test_sparse_occupancy_rejects_bad_content():
    pts, labels = _occ()
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValidationError, match="non-finite"):
        SparseOccupancy.from_points(bad, labels, OCC3D_GRID)
    with pytest.raises(ValidationError, match="labels out of range"):
        SparseOccupancy.from_points(pts, np.full(10, 18, np.uint8), OCC3D_GRID)
    with pytest.raises(ValidationError, match="outside the grid"):
        SparseOccupancy.from_points(pts + [100, 0, 0], labels, OCC3D_GRID)
    with pytest.raises(ValidationError, match=r"labels must be \(10,\)"):
        SparseOccupancy.from_points(pts, labels[:9], OCC3D_GRID)
    idx = np.full((2, 3), 250, np.uint8)
    with pytest.raises(ValidationError, match="outside the grid shape"):
        SparseOccupancy(voxels=Array.from_numpy(idx), labels=Array.from_numpy(np.zeros(2, np.uint8)))
    with pytest.raises(ValidationError, match="exactly one"):
        SparseOccupancy(labels=Array.from_numpy(np.zeros(0, np.uint8)))


def _image(encoding="raw_rgb8", w=4, h=3):
    return CameraImage(
        camera="CAM_FRONT",
        encoding=encoding,
        width=w,
        height=h,
        data=bytes(w * h * 3),
        intrinsics=np.eye(3).tolist(),
        extrinsics=np.eye(4).tolist(),
    )


def test_camera_frame_needs_six_or_no_images_and_finite_calibration():
    CameraFrame(stream="s", seq=0, stamp=0.0, images=[_image()] * 6)
    with pytest.raises(ValidationError, match="6 images"):
        CameraFrame(stream="s", seq=0, stamp=0.0, images=[_image()] * 5)
    with pytest.raises(ValidationError, match="non-finite"):
        CameraImage(
            camera="c",
            encoding="png",
            width=1,
            height=1,
            data=b"x",
            intrinsics=[[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]],
            extrinsics=np.eye(4).tolist(),
        )
    with pytest.raises(ValidationError, match="needs 36 bytes"):
        CameraImage(
            camera="c",
            encoding="raw_rgb8",
            width=4,
            height=3,
            data=b"x",
            intrinsics=np.eye(3).tolist(),
            extrinsics=np.eye(4).tolist(),
        )
    with pytest.raises(ValidationError, match="stream"):
        CameraFrame(stream="a/b", seq=0, stamp=0.0)
    with pytest.raises(ValidationError):
        CameraFrame(stream="s", seq=-1, stamp=0.0)
    with pytest.raises(ValidationError):
        CameraFrame(stream="s", seq=0, stamp=float("nan"))


def test_pose_estimate_checks_matrix_and_status():
    p = PoseEstimate(
        stream="s", seq=1, stamp=0.5, pose=np.eye(4).tolist(), status="ok", timings_ms={"registration": 3.0}
    )
    assert np.array_equal(p.matrix(), np.eye(4))
    with pytest.raises(ValidationError, match="4x4"):
        PoseEstimate(stream="s", seq=1, stamp=0.5, pose=np.eye(3).tolist(), status="ok")
    bad = np.eye(4)
    bad[0, 3] = np.inf
    with pytest.raises(ValidationError, match="non-finite"):
        PoseEstimate(stream="s", seq=1, stamp=0.5, pose=bad.tolist(), status="ok")
    with pytest.raises(ValidationError):
        PoseEstimate(stream="s", seq=1, stamp=0.5, pose=np.eye(4).tolist(), status="fine")


def test_map_tile_checks_arrays():
    pts, labels = _occ(5)
    MapTile(stream="s", ix=0, iy=-1, tile_m=20, seq=3, points=Array.from_numpy(pts), labels=Array.from_numpy(labels))
    with pytest.raises(ValidationError, match=r"\(M,3\) float64"):
        MapTile(
            stream="s",
            ix=0,
            iy=0,
            tile_m=20,
            seq=3,
            points=Array.from_numpy(pts.astype(np.float32)),
            labels=Array.from_numpy(labels),
        )
    with pytest.raises(ValidationError, match="uint8"):
        MapTile(
            stream="s", ix=0, iy=0, tile_m=20, seq=3, points=Array.from_numpy(pts), labels=Array.from_numpy(labels[:4])
        )


def test_other_messages_construct():
    MapUpdate(stream="s", seq=0, reset=True, tile_m=20.0)
    MapInfo(stream="s", tile_m=20, tile_count=0, voxel_count=0, last_seq=None, bounds_min=None, bounds_max=None)
    ErrorEvent(stream="s", worker="w", code="malformed", message="x")
    WorkerHealth(worker="w", role="map", pid=1, uptime_s=0, policy="latest", streams=[], counters={})
    OccupancyFrameMsg(
        stream="s", seq=0, stamp=0, source="replay", occupancy=SparseOccupancy.from_points(*_occ(), OCC3D_GRID)
    )
    with pytest.raises(ValidationError):
        ErrorEvent(stream="s", worker="w", code="no_such_code", message="x")


def test_keys():
    assert keys.camera("car0") == "occvo/car0/camera"
    assert keys.pose_latest("car0") == "occvo/car0/pose/latest"
    assert keys.map_tile("car0", -2, 3) == "occvo/car0/map/tile/-2/3"
    assert keys.stream_of("occvo/car0/map/tile/1/2") == "car0"
    assert keys.stream_of("occvo/@workers/w/stats") == "*"
    assert keys.tile_of("occvo/car0/map/tile/-2/3") == (-2, 3)
    assert keys.tile_of("occvo/car0/map/tile/*/3") is None
    assert keys.alive("map", "w1") == "occvo/@alive/map/w1"
    with pytest.raises(ValueError):
        keys.check_stream("a/b")
