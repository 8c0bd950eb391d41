from pathlib import Path

import numpy as np
import pytest

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "occvo-sample"


@pytest.fixture(scope="session")
def sample_root() -> Path:
    if not (SAMPLE / "occupancy").is_dir():
        pytest.skip(f"real nuScenes sample not found at {SAMPLE} (it sits beside the checkout in CI, not in a fresh clone)")
    return SAMPLE


@pytest.fixture(scope="session")
def scene_0101(sample_root):
    from occvo_core.datasets import OccVOReleaseScene

    return OccVOReleaseScene(sample_root / "occupancy" / "scene-0101")


def random_pose(rng: np.random.Generator, max_angle_rad: float, max_shift_m: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    axis = rng.normal(size=3)
    pose[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0, max_angle_rad)).as_matrix()
    pose[:3, 3] = rng.uniform(-max_shift_m, max_shift_m, 3)
    return pose
