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


class FirstFrames:
    """The first n frames of a source, with its ground truth and every other attribute (`occvo run --frames N`)."""

    def __init__(self, source: SceneSource, n: int):
        self.source, self.n = source, min(int(n), len(source))

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, index: int) -> OccupancyFrame:
        if not 0 <= index < self.n:
            raise IndexError(index)
        return self.source[index]

    @property
    def gt_poses(self) -> np.ndarray | None:
        gt = self.source.gt_poses
        return None if gt is None else gt[: self.n]

    def __getattr__(self, name: str):
        return getattr(self.source, name)
