"""OccVO's state as named arrays, for durable storage and restarts (the store itself lives outside occvo_core):
config, poses, frame indices, the voxel pfilter map, loop closure and the last frame."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from occvo_core.config import OccVOConfig
from occvo_core.errors import ConfigError
from occvo_core.registration.preprocess import Prepared
from occvo_core.registration.voxel_rows import stored_rows

if TYPE_CHECKING:
    from occvo_core.odometry import OccVO


def state_dict(vo: OccVO, copy: bool = True) -> dict[str, np.ndarray]:
    """Everything needed to resume. copy=False gives views of the map arrays, for a caller that writes them out
    before the next step."""
    out = {
        "config_json": np.frombuffer(vo.config.model_dump_json().encode(), np.uint8),
        "poses": vo.poses,
        "indices": np.array(vo.frame_indices, np.int64),
    }
    out.update({f"map.{k}": v for k, v in vo.map.state(copy).items()})
    out.update(vo.loop_closure.state())
    if vo._last is not None:
        out.update({f"last.{k}": np.asarray(v) for k, v in vars(vo._last).items()})
    return out


def stored(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """state_dict()'s arrays in the form a store keeps (voxel_rows.stored_rows: a third smaller); load_state_dict
    takes either form."""
    rows = stored_rows({k[4:]: v for k, v in state.items() if k.startswith("map.")})
    return {k: v for k, v in state.items() if not k.startswith("map.")} | {f"map.{k}": v for k, v in rows.items()}


def check_config(state: dict[str, np.ndarray], config: OccVOConfig) -> None:
    """Refuse a state made with another config: its map and poses would not be this config's."""
    saved = bytes(np.asarray(state["config_json"], np.uint8)).decode()
    try:  # compared as configs, not text: a section added since takes its default
        same = OccVOConfig.model_validate_json(saved) == config
    except ValueError:
        same = False
    if not same:
        raise ConfigError(
            f"saved odometry state was made with another OccVOConfig; refusing to mix them (saved: {saved})"
        )


def load_state_dict(vo: OccVO, state: dict[str, np.ndarray]) -> None:
    """Resume from state_dict(); the next step() continues bit for bit as if the run had never stopped."""
    check_config(state, vo.config)
    vo.reset()
    vo.map.load_state({k[4:]: np.asarray(v) for k, v in state.items() if k.startswith("map.")})
    poses = [np.array(p, np.float64) for p in np.asarray(state["poses"]).reshape(-1, 4, 4)]
    last = None
    if "last.points" in state:
        fields = {k[5:]: np.asarray(v) for k, v in state.items() if k.startswith("last.")}
        fields["index"] = int(fields["index"])
        last = Prepared(**fields)
    vo._resume(poses, [int(i) for i in state["indices"]], last)
    vo.loop_closure.load_state(state, len(poses))
