"""A run over part of a scene: frames first..last of any scene source as a scene of their own (frame 0 = `first`),
so that odometry starts there with nothing of the frames before it; ground truth sliced to match."""

from __future__ import annotations

import dataclasses

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame


class FrameRange:
    """Frames `first`..`last` (inclusive) of `source`; other attributes (the predictor, the plane rule) are the
    source's."""

    def __init__(self, source, first: int, last: int):
        if not 0 <= first <= last < len(source):
            raise ConfigError(f"frames {first}-{last}: the scene has frames 0-{len(source) - 1}")
        self.source, self.first, self.last = source, int(first), int(last)
        self.name = f"{source.name}[{first}-{last}]"

    def __getattr__(self, name: str):
        return getattr(self.source, name)  # only what this class does not define itself

    def __len__(self) -> int:
        return self.last - self.first + 1

    def __getitem__(self, index: int) -> OccupancyFrame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        frame = self.source[self.first + index]
        return dataclasses.replace(frame, index=index, meta={**frame.meta, "source_index": frame.index})

    @property
    def gt_poses(self) -> np.ndarray | None:
        gt = self.source.gt_poses
        return None if gt is None else np.asarray(gt)[self.first : self.last + 1]

    @property
    def stamps(self) -> np.ndarray | None:
        stamps = getattr(self.source, "stamps", None)
        return None if stamps is None else np.asarray(stamps)[self.first : self.last + 1]
