"""One typed configuration for the whole odometry, with the paper's defaults and names."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GICPConfig(_Section):
    wide_voxel_m: float = Field(
        2.4,
        ge=0,
        description="first coarse pass with map pooling, source thinning and "
        "correspondence limit all this size: nuScenes keyframe intervals jitter by a third, so the "
        "constant-velocity guess can be 2 m off; 0 = no wide pass",
    )
    k_neighbours_radius_voxels: int = Field(
        2,
        ge=1,
        le=3,
        description="covariance from the (2r+1)^3 voxel neighbourhood on the grid: a plane fitted to 3 x 3 x 3 "
        "voxel centres takes the lattice's steps for its slope",
    )
    covariance_epsilon: float = Field(
        3e-2,
        gt=0,
        description="plane regularisation: eigenvalues (eps, 1, 1), Segal et al.; a normal fitted to voxel "
        "centres quantised on the ego grid is unsure, so less than Segal's 1e-3 weight rests on it",
    )
    coarse_max_correspondence_m: float = Field(1.2, gt=0)
    wide_trust_m: float = Field(
        0.6,
        ge=0,
        description="a wide pass that moves the guess less than this (and turns it "
        "under 2 degrees) is coarse GICP's only start; farther, coarse GICP also starts from the "
        "guess (see wide_pairs_margin): a wide pass far off can lead coarse GICP on into a "
        "neighbouring minimum",
    )
    wide_pairs_margin: float = Field(
        0.1,
        ge=0,
        description="from two starts, the wide pass's alignment replaces the "
        "guess's only when it keeps this share more pairs (at about equal support the "
        "guess, the prior, stays)",
    )
    coarse_map_voxel_m: float = Field(1.2, gt=0, description="coarse GICP pairs with the map pooled on this grid")
    fine_max_correspondence_m: float = Field(0.6, gt=0)
    coarse_iterations: int = Field(12, ge=1)
    fine_iterations: int = Field(10, ge=1)
    convergence_rotation_rad: float = Field(3e-4, gt=0)
    convergence_translation_m: float = Field(3e-3, gt=0)
    correspondence_reuse: float = Field(
        0.25,
        ge=0,
        description="search nearest neighbours again only once a point may "
        "have moved this share of a map voxel since the last search; 0 = every iteration",
    )
    robust_kernel_scale: float = Field(
        0.0, ge=0, description="Cauchy scale on the Mahalanobis error; 0 = least squares"
    )
    source_voxel_m: float = Field(0.8, gt=0, description="fine GICP uses one frame point per block of this size")
    ground_source_voxel_m: float = Field(
        1.6, gt=0, description="the same for ground classes, which hold only z, roll, pitch"
    )
    coarse_source_voxel_m: float = Field(
        1.6, gt=0, description="coarse GICP uses one frame point per block of this size"
    )
    source_pick: Literal["first", "balanced", "uniform"] = Field(
        "uniform",
        description="which voxel of a block is its source: uniform (a fixed hash of the voxel's grid cell "
        "decides, so every voxel is as likely and the picks lean no way in the ego frame), first (the first in grid "
        "order: the rear-most, lowest ego x) or balanced (the front-most in every other block)",
    )


class SemanticLabelFilterConfig(_Section):
    enabled: bool = True


class DynamicObjectFilterConfig(_Section):
    enabled: bool = True
    displacement_threshold_m: float = Field(
        2.0, gt=0, description="objects farther than this from their map counterpart are dynamic"
    )
    min_cluster_voxels: int = Field(5, ge=1, description="smaller clusters of movable voxels are not judged")
    cluster_eps_m: float = Field(1.0, gt=0, description="single-linkage distance that joins voxels into one object")
    displacement_quantile: float = Field(0.8, gt=0, le=1, description="robust max of an object's point distances")


class VoxelPFilterConfig(_Section):
    enabled: bool = True
    p_index_threshold: float = Field(
        0.5, ge=0, le=1, description="only map voxels with p-index above this constrain registration"
    )
    map_voxel_m: float = Field(0.4, gt=0)
    merge_radius_m: float = Field(
        0.2, ge=0, description="a frame point joins the nearest map point this close, else its own voxel"
    )
    observe_radius_m: float = Field(
        0.45,
        ge=0,
        description="a voxel counts as seen when a frame point lands this close (one voxel pitch: frames are quantised on their own ego grid)",
    )
    window_margin_m: float = Field(
        4.0, ge=0, description="map kept around the frame's box for registration and merging"
    )


class InitialisationConfig(_Section):
    bev_search_radius_m: float = Field(12.0, ge=0, description="first-motion search window of the BEV correlation")
    bev_yaw_steps_deg: tuple[float, ...] = (-6.0, -3.0, 0.0, 3.0, 6.0)
    use_constant_velocity: bool = True
    motion_search: bool = Field(
        False,
        description="each frame, the constant-velocity guess is refined by a semantic "
        "BEV correlation with the previous frame (semantic_bev_motion): it follows turns "
        "that start or end between frames, which GICP on a network's occupancy does not. "
        "Off by default: it costs time every frame, and on ground-truth occupancy GICP "
        "follows turns without it (occvo run --from-images switches it on)",
    )
    motion_search_yaw_deg: float = Field(16.0, ge=0, description="the search turns the guess this far either way")
    motion_search_step_deg: float = Field(2.0, gt=0)
    motion_search_radius_m: float = Field(4.0, ge=0, description="and moves it this far")
    motion_search_prior_m: float = Field(
        1.0,
        gt=0,
        description="Gaussian prior (sigma) on that move: along a straight "
        "road the correlation is flat, and a network's ego-bound voxels would pull "
        "it to no motion",
    )


class LoopClosureConfig(_Section):
    """Relocalisation against the map of a place seen long ago (not in the paper: its scenes are 20 s long, but a
    long drive that comes back to its start does so with metres of drift, beyond any GICP basin)."""

    enabled: bool = True
    min_gap_frames: int = Field(100, ge=1, description="voxels made at least this many frames ago are the old map")
    min_old_voxels: int = Field(
        3000, ge=1, description="reliable old voxels within the frame's box before a loop is looked for"
    )
    lock_share: float = Field(
        0.3,
        ge=0,
        le=1,
        description="a frame with this share of its fine sources on the old map "
        "(same label, within the fine correspondence distance) follows it: no search, the old map "
        "constrains the next registration whatever its p-index, the frame's points on it count as "
        "sightings, its other voxels are dropped before they would be old (a frame off it would "
        "only drag it), and the map made since drifted no more",
    )
    accept_share: float = Field(
        0.6,
        ge=0,
        le=1,
        description="a loop is closed when the relocalised frame puts at least "
        "this share of its fine sources where the old map is on it (and twice the share of "
        "all its sources as before)",
    )
    min_overlap: float = Field(
        0.25,
        ge=0,
        le=1,
        description="... and at least this share of them has old map within "
        "twice the coarse correspondence distance (the frame overlaps the old place)",
    )
    min_correction_m: float = Field(
        1.0, ge=0, description="smaller corrections are left to registration (its wide pass reaches 2.4 m)"
    )
    search_radius_m: float = Field(24.0, gt=0, description="BEV correlation window around the registered pose")
    search_height_m: float = Field(
        8.0,
        ge=0,
        description="the search also reaches this far up and down (height drifts "
        "too; the frame's ground is then levelled on the old map's)",
    )
    search_every_frames: int = Field(
        5,
        ge=1,
        description="after a search, the next one waits this many frames (a "
        "search costs tens of ms; many streams share the worker's cores)",
    )
    yaw_steps_deg: tuple[float, ...] = (-4.0, -2.0, 0.0, 2.0, 4.0)
    ghost_radius_m: float = Field(
        1.0,
        ge=0,
        description="after a closure, a corrected voxel this close to one of the "
        "anchor's map with its label is that voxel seen through drift, and is dropped",
    )


class OccVOConfig(_Section):
    max_range_m: float | None = Field(
        None, gt=0, description="frame points farther than this (horizontally) are not used"
    )
    gicp: GICPConfig = GICPConfig()
    semantic_label_filter: SemanticLabelFilterConfig = SemanticLabelFilterConfig()
    dynamic_object_filter: DynamicObjectFilterConfig = DynamicObjectFilterConfig()
    voxel_pfilter: VoxelPFilterConfig = VoxelPFilterConfig()
    initialisation: InitialisationConfig = InitialisationConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()

    @classmethod
    def load(cls, path: str | Path, defaults: dict | None = None) -> OccVOConfig:
        """From a JSON or YAML-free JSON5 file; unknown keys are an error. `defaults` (a scene source's own) stand
        where the file says nothing."""
        from occvo_core import config_file

        return config_file.validate(cls, _deep_merge(defaults or {}, config_file.read(path)), path)

    def with_filters(self, semantic: bool = True, dynamic: bool = True, pfilter: bool = True) -> OccVOConfig:
        return self.model_copy(
            update={
                "semantic_label_filter": SemanticLabelFilterConfig(enabled=semantic),
                "dynamic_object_filter": self.dynamic_object_filter.model_copy(update={"enabled": dynamic}),
                "voxel_pfilter": self.voxel_pfilter.model_copy(update={"enabled": pfilter}),
            }
        )

    def with_motion_search(self, enabled: bool = True) -> OccVOConfig:
        return self.model_copy(
            update={"initialisation": self.initialisation.model_copy(update={"motion_search": enabled})}
        )


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out
