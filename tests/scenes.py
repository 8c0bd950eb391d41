"""Small hand-built occupancy scenes on the Occ3D grid, with answers known by construction."""

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID


def box(lo, hi, label):
    """Voxel centres filling the axis-aligned box [lo, hi] (metres, ego frame), all with one label."""
    g = OCC3D_GRID
    i0, i1 = g.indices_of(np.array([lo, hi]))
    ii = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(i0, i1)], indexing="ij"), -1).reshape(-1, 3)
    ii = ii[g.inside(ii)]
    return g.centres_of(ii), np.full(len(ii), label, np.uint8)


def town(objects=()):
    """Ground, two building rows with gaps, poles and vegetation: structure in every direction; plus extra boxes."""
    parts = [box((-39.9, -39.9, -0.9), (39.9, 39.9, -0.9), 11)]  # driveable surface
    for x0 in range(-38, 38, 12):
        parts.append(box((x0, 9, -0.5), (x0 + 7, 13, 3 + (x0 % 5)), 15))  # buildings north
        parts.append(box((x0 + 3, -15, -0.5), (x0 + 9, -10, 2 + (x0 % 3)), 15))  # buildings south
    for x in range(-36, 37, 9):
        parts.append(box((x, 7, -0.5), (x + 0.3, 7.3, 4), 15))  # poles
        parts.append(box((x + 4, -8.5, -0.5), (x + 5.5, -7.5, 2.5), 16))  # trees
    parts.extend(objects)
    pts = np.concatenate([p for p, _ in parts])
    lab = np.concatenate([l for _, l in parts])
    _, unique = np.unique(OCC3D_GRID.indices_of(pts), axis=0, return_index=True)
    return pts[unique], lab[unique]


def frame(points, labels, index=0):
    return OccupancyFrame(points.copy(), labels.copy(), index=index)


def car(x, y, label=4):
    return box((x, y, -0.5), (x + 4.2, y + 1.8, 1.0), label)


def shell(points):
    """The voxels of points with an empty face neighbour (what the odometry keeps of solid objects)."""
    from occvo_core.registration.kernels.grid import surface_voxels

    return points[surface_voxels(OCC3D_GRID.indices_of(points), np.array(OCC3D_GRID.shape))]
