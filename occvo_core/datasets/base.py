"""What every scene source offers: indexed occupancy frames, and ground-truth poses when known."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol, runtime_checkable

import numpy as np

from occvo_core.frame import OccupancyFrame


@runtime_checkable
class SceneSource(Protocol):
    name: str
    rate_hz: float

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> OccupancyFrame: ...

    @property
    def gt_poses(self) -> np.ndarray | None:
        """(N,4,4) ego-to-world poses, or None when the scene has no ground truth."""
        ...


def iterate(source: SceneSource) -> Iterator[OccupancyFrame]:
    for i in range(len(source)):
        yield source[i]
