"""Occupancy from LiDAR, after Occ3D's recipe: points labelled by the boxes they fall in and by ground geometry,
voxelised on the 0.4 m grid (docs/datasets.md has the recipe and where it differs from Occ3D's)."""
