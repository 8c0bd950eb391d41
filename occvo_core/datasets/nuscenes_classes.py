"""nuScenes box categories -> Occ3D-nuScenes classes, as nuScenes-lidarseg's 16-class benchmark maps them (Occ3D's
labels come from that map); a category it ignores (animal, emergency vehicles, debris, pushable objects, bicycle
racks, personal mobility, strollers, wheelchairs) is class 0, others."""

from __future__ import annotations

_PREFIXES = (
    ("movable_object.barrier", 1),
    ("vehicle.bicycle", 2),
    ("vehicle.bus", 3),
    ("vehicle.car", 4),
    ("vehicle.construction", 5),
    ("vehicle.motorcycle", 6),
    ("human.pedestrian.adult", 7),
    ("human.pedestrian.child", 7),
    ("human.pedestrian.construction_worker", 7),
    ("human.pedestrian.police_officer", 7),
    ("movable_object.trafficcone", 8),
    ("vehicle.trailer", 9),
    ("vehicle.truck", 10),
)


def occ3d_class(category: str) -> int:
    """The Occ3D class of a nuScenes category name (e.g. 'vehicle.bus.rigid' -> 3 bus)."""
    for prefix, label in _PREFIXES:
        if category == prefix or category.startswith(prefix + "."):
            return label
    return 0
