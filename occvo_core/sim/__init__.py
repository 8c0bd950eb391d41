"""A seeded procedural town emitting Occ3D occupancy frames as a surround-camera occupancy network would.

    scene = SyntheticScene(seed=0, frames=40, rate_hz=2.0, noise="default", traffic=True)
    frame = scene[0]                 # OccupancyFrame, ego frame, camera-visible voxels with prediction noise
    scene.gt_poses                   # (N,4,4) ego->world
    scene.static_map()               # true static world map (world frame), scene.dynamic_tracks()
    scene.true_grid(i)               # noise-free (200,200,16) uint8 before visibility; scene.camera_mask(i)
    export_release(scene, root) / export_occ3d(scene, root)   # occvo_core.sim.export
    loop = SyntheticScene(seed=0, frames=3600, route="loop", loop_blocks=(4, 4))   # laps of a ~1.1 km block circuit
    loop.lap_starts, loop.lap_length_m   # frames at which each lap begins (ego back at its start); circuit length

The town: a road graph of straight and bowed roads meeting at intersections (driveable surface), sidewalks
raised by a kerb, terrain, buildings, walls, site cabins (manmade), street lights, signs, barriers and cones,
street trees, hedges and parks (vegetation), parking lots and parking lanes with parked cars, trucks,
trailers, buses, motorcycles and bicycles (static), and moving vehicles and pedestrians (dynamic).
The ego drives 0-15 m/s with a stop and a turn at the first intersection; frames at `rate_hz`.
On a loop the town covers only the circuit plus the sensor range, traffic drives the circuit (ahead of the ego in
its lane, oncoming in the other), and drives of more than 500 frames keep only 8 rendered frames and no per-frame
static bookkeeping (memory does not grow with the drive; see SyntheticScene's cache_frames / keep_static).
"""

from occvo_core.sim.agents import DynamicTrack
from occvo_core.sim.noise import NoiseModel
from occvo_core.sim.scene import CAMERAS, LIDAR, SyntheticScene

__all__ = ["SyntheticScene", "NoiseModel", "DynamicTrack", "CAMERAS", "LIDAR"]
