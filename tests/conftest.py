import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from occvo_core.reproducible import restart_pinned

LOGINS_DIR_ENV = "OCCVO_LOGINS_DIR"  # services/logins.py (tests/core runs without the services' zenoh)
_LOGINS: list[str] = []


def pytest_configure(config):
    """The suite checks exact poses, digests and model scores: it runs in one floating-point environment on every
    x86-64 machine (an AVX-512 CPU rounds numpy's sin and cos differently). The pins act when numpy loads, so pytest
    starts again with them (here, where its output capture is not yet on)."""
    restart_pinned()
    # the logins `occvo serve` makes on a first start (services/logins.py) go to a folder of this run's, not to the
    # user's ~/.config/occvo: set before any test module is imported (some copy os.environ for their processes)
    _LOGINS.append(tempfile.mkdtemp(prefix="occvo-test-logins-"))
    os.environ[LOGINS_DIR_ENV] = _LOGINS[0]


def pytest_unconfigure(config):
    for folder in _LOGINS:
        shutil.rmtree(folder, ignore_errors=True)


SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "occvo-sample"
SERVICE_FRAMES = 12  # frames of `scene`, the synthetic drive the service tests stream (a module may define its own)


@pytest.fixture(scope="session")
def sample_root() -> Path:
    if not (SAMPLE / "occupancy").is_dir():
        pytest.skip(
            f"real nuScenes sample not found at {SAMPLE} (it sits beside the checkout in CI, not in a fresh clone)"
        )
    return SAMPLE


@pytest.fixture(scope="session")
def drive_root() -> Path:
    """The shared real nuScenes drive's folder (skips where it is absent)."""
    from nuscenes_sample import drive_root

    return drive_root()


@pytest.fixture(scope="session")
def drive(drive_root):
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive

    return NuScenesDrive(drive_root, "scene-0916")


@pytest.fixture(scope="session")
def scene_0101(sample_root):
    from occvo_core.datasets import OccVOReleaseScene

    return OccVOReleaseScene(sample_root / "occupancy" / "scene-0101")


@pytest.fixture(scope="session")
def scene():
    from occvo_core.sim import SyntheticScene

    s = SyntheticScene(seed=5, frames=SERVICE_FRAMES)
    return [s[i] for i in range(SERVICE_FRAMES)]


@pytest.fixture(scope="session")
def uninterrupted(scene):
    """OccVO's poses over `scene` in this process: what a service run of it must reproduce bit for bit."""
    from occvo_core import OccVO

    vo = OccVO()
    for f in scene:
        vo.step(f)
    return vo.poses


def random_pose(rng: np.random.Generator, max_angle_rad: float, max_shift_m: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    axis = rng.normal(size=3)
    pose[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0, max_angle_rad)).as_matrix()
    pose[:3, 3] = rng.uniform(-max_shift_m, max_shift_m, 3)
    return pose


@pytest.fixture(scope="session")
def pg_cluster():
    """A PostgreSQL 15 server of the session's own (services/store/pg_local.py); its restart tests stop and start it."""
    from occvo_services.store.pg_local import PgCluster, missing

    why = missing()
    if why:
        pytest.skip(why)
    cluster = PgCluster()
    yield cluster
    cluster.close()


@pytest.fixture
def pg_url(pg_cluster) -> str:
    """The URL of a new, empty database on the session's server."""
    return pg_cluster.new_database()


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request, tmp_path) -> str:
    """A new store of each backend: a SQLite file, a PostgreSQL database (a test using it runs on both)."""
    return str(tmp_path / "s.sqlite") if request.param == "sqlite" else request.getfixturevalue("pg_url")
