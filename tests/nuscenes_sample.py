"""Where the tests find the shared real nuScenes drive (scene-0916), and the skip where it is absent."""

from pathlib import Path

import pytest

DRIVE = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini"


def drive_root() -> Path:
    if not (DRIVE / "v1.0-mini" / "scene.json").is_file():
        pytest.skip(f"the real nuScenes drive is not at {DRIVE} (it sits beside the checkout in CI)")
    return DRIVE
