"""The registration pieces of OCC-VO: GICP, the semantic label filter (inside GICP's pairing), the dynamic object
filter, the voxel pfilter map and the first-motion initialisation."""
