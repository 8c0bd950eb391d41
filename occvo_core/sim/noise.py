"""A prediction noise model imitating an occupancy network's errors on the camera-visible voxels.

Each error kind has a base rate that grows linearly with horizontal distance from the ego:
rate(d) = base * (1 + distance_gain * min(d, 40 m) / 40 m), capped at 1. Errors, in order:
  drop            a visible occupied voxel is missed (set free);
  confusion       a kept voxel takes a neighbouring class (road <-> sidewalk <-> terrain, manmade <-> vegetation, car <-> truck ...);
  jitter          a thin structure's column (<= `thin_max_neighbours` occupied of its 8 horizontal neighbours at that height
                  in the noise-free grid: poles, trunks, cones, sign plates, pedestrians)
                  moves by one voxel in x or y, all its voxels together;
  false_positive  a visible free voxel face-adjacent to a visible occupied one becomes occupied with that neighbour's class,
                  independently in each frame (transient).
Draws come from a generator seeded by (scene seed, frame index), so a frame's noise does not depend on access order.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.sim.raster import hash_uniform
from occvo_core.sim.render import horizontal_neighbours, nonzero3, surface_free_voxels


def occupied_indices(grid: np.ndarray) -> np.ndarray:
    return nonzero3(grid, np.uint8(FREE), False)


# Classes an occupancy network confuses with each other (Occ3D ids).
CONFUSION_NEIGHBOURS: dict[int, tuple[int, ...]] = {
    0: (15,),
    1: (15, 8),
    2: (6, 7),
    3: (10, 4),
    4: (10, 3),
    5: (10, 4),
    6: (2, 4),
    7: (2, 0),
    8: (1,),
    9: (10,),
    10: (4, 3, 9),
    11: (13, 12),
    12: (11, 13),
    13: (11, 14, 12),
    14: (13, 16),
    15: (16, 1),
    16: (14, 15),
}


class NoiseModel(BaseModel):
    """Rates are probabilities per voxel at the ego (d = 0); see the module doc for their meaning."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    drop_rate: float = Field(0.0, ge=0, le=1, description="visible occupied voxels missed")
    confusion_rate: float = Field(0.0, ge=0, le=1, description="kept voxels given a neighbouring class")
    false_positive_rate: float = Field(
        0.0, ge=0, le=1, description="visible free voxels next to a surface turned occupied"
    )
    jitter_rate: float = Field(0.0, ge=0, le=1, description="thin-structure columns moved by one voxel")
    distance_gain: float = Field(0.0, ge=0, description="rates at 40 m are (1 + gain) times the base rate")
    thin_max_neighbours: int = Field(
        3, ge=0, le=8, description="a voxel is thin with at most this many occupied horizontal neighbours"
    )
    persistence: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of drop and confusion draws tied to the world voxel, so "
        "the same place fails again in the next frames as a network's systematic errors do",
    )
    patch_m: float = Field(
        0.8, gt=0, description="world cell size of the persistent draws: errors come in patches this big"
    )

    @classmethod
    def preset(cls, name: Literal["none", "default", "heavy"] | str) -> NoiseModel:
        try:
            return cls(**PRESETS[name])
        except KeyError:
            raise ValueError(f"unknown noise preset {name!r}; choose one of {sorted(PRESETS)}") from None

    @classmethod
    def coerce(cls, noise: NoiseModel | str | dict | None) -> NoiseModel:
        if noise is None:
            return cls.preset("none")
        if isinstance(noise, NoiseModel):
            return noise
        if isinstance(noise, str):
            return cls.preset(noise)
        return cls.model_validate(noise)

    @property
    def is_clean(self) -> bool:
        return not (self.drop_rate or self.confusion_rate or self.false_positive_rate or self.jitter_rate)

    def rate(self, base: float, distance: np.ndarray) -> np.ndarray:
        return np.minimum(base * (1.0 + self.distance_gain * np.minimum(distance, 40.0) / 40.0), 1.0)

    def apply(
        self,
        semantics: np.ndarray,
        seen: np.ndarray,
        rng: np.random.Generator,
        pose: np.ndarray | None = None,
        seed: int = 0,
    ) -> np.ndarray:
        """Noisy labels of the visible voxels: returns a (200,200,16) grid, free outside `seen` except false positives.
        `pose` (ego->world) and `seed` anchor the persistent share of the draws to world voxels."""
        out = np.where(seen, semantics, FREE).astype(np.uint8)
        if self.is_clean:
            return out
        shape = np.array(out.shape)
        truth = out != FREE
        occ = occ0 = occupied_indices(out)  # sparse from here on: the visible occupied voxels

        def dist(idx):
            c = OCC3D_GRID.centres_of(idx)
            return np.hypot(c[:, 0], c[:, 1])

        def draw(idx, salt):
            u = rng.random(len(idx))
            if self.persistence > 0 and pose is not None and len(idx):
                world = OCC3D_GRID.centres_of(idx) @ pose[:3, :3].T + pose[:3, 3]
                a = 1.1 + 0.7 * (seed % 7)  # patch lattice turned per scene, not lined up with the roads
                c, s_ = np.cos(a), np.sin(a)
                world = np.column_stack(
                    [c * world[:, 0] - s_ * world[:, 1], s_ * world[:, 0] + c * world[:, 1], world[:, 2]]
                )
                w = np.floor(world / self.patch_m).astype(np.int64)
                anchored = hash_uniform(seed, w[:, 0], w[:, 1], w[:, 2], salt=salt + 100) < self.persistence
                u = np.where(anchored, hash_uniform(seed, w[:, 0], w[:, 1], w[:, 2], salt=salt), u)
            return u

        if self.jitter_rate > 0 and len(occ):
            # thinness from the whole structure, not just its visible face
            nb = horizontal_neighbours(semantics != FREE, occ)
            thin = occ[nb <= self.thin_max_neighbours]
            cols, col_of = np.unique(thin[:, 0] * shape[1] + thin[:, 1], return_inverse=True)
            col_ij = np.column_stack([cols // shape[1], cols % shape[1]])
            move = rng.random(len(cols)) < self.rate(
                self.jitter_rate, dist(np.column_stack([col_ij, np.zeros(len(cols), int)]))
            )
            step = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])[rng.integers(0, 4, len(cols))]
            moved = thin[move[col_of]]
            target = moved + step[col_of[move[col_of]]]
            labels = out[moved[:, 0], moved[:, 1], moved[:, 2]]
            out[moved[:, 0], moved[:, 1], moved[:, 2]] = FREE
            ok = np.all((target >= 0) & (target < shape), axis=1)
            target, labels = target[ok], labels[ok]
            free = out[target[:, 0], target[:, 1], target[:, 2]] == FREE
            out[target[free, 0], target[free, 1], target[free, 2]] = labels[free]
            occ = occupied_indices(out)
        if self.drop_rate > 0 and len(occ):
            drop = draw(occ, 1) < self.rate(self.drop_rate, dist(occ))
            out[occ[drop, 0], occ[drop, 1], occ[drop, 2]] = FREE
            occ = occ[~drop]
        if self.confusion_rate > 0 and len(occ):
            swapped = draw(occ, 2) < self.rate(self.confusion_rate, dist(occ))
            swap = occ[swapped]
            old = out[swap[:, 0], swap[:, 1], swap[:, 2]]
            pick = draw(swap, 3)
            new = old.copy()
            for c, options in CONFUSION_NEIGHBOURS.items():
                m = old == c
                if m.any():
                    new[m] = np.array(options, np.uint8)[
                        np.minimum((pick[m] * len(options)).astype(int), len(options) - 1)
                    ]
            out[swap[:, 0], swap[:, 1], swap[:, 2]] = new
        if self.false_positive_rate > 0:
            cand, labels = surface_free_voxels(occ0, truth, seen, semantics)
            on = rng.random(len(cand)) < self.rate(self.false_positive_rate, dist(cand))
            sel = cand[on]
            out[sel[:, 0], sel[:, 1], sel[:, 2]] = labels[on]
        return out


def false_positive_candidates(occupied: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(K,3) indices, in grid order, of visible free voxels with an occupied face neighbour."""
    occ = nonzero3(occupied, True, True)
    return surface_free_voxels(occ, occupied, seen, np.zeros(occupied.shape, np.uint8))[0]


PRESETS: dict[str, dict] = {
    "none": {},
    # Near TPV-Former on Occ3D-nuScenes, calibrated on the OCC-VO sample (the paper's network-predicted occupancy) with
    # benchmarks/noise_calibration.py, which prints the two measures for the sample and for these knobs: the share of
    # static voxels within 0.4 m of the previous frame's (moved by the true pose) and the share of matched voxels that
    # keep their class (geometry scores lower than the sample's because synthetic frames are visibility-limited).
    # Network errors are mostly systematic, hence the high persistence. Rates at the ego.
    "default": {
        "drop_rate": 0.12,
        "confusion_rate": 0.05,
        "false_positive_rate": 0.005,
        "jitter_rate": 0.1,
        "distance_gain": 1.0,
        "persistence": 0.97,
        "patch_m": 0.8,
    },
    # Transient, frequent errors: a weak network, or a good one in rain and at night.
    "heavy": {
        "drop_rate": 0.25,
        "confusion_rate": 0.15,
        "false_positive_rate": 0.03,
        "jitter_rate": 0.4,
        "distance_gain": 2.0,
        "persistence": 0.5,
        "patch_m": 0.8,
    },
}
