"""The boxes of OCC-VO's Fig. 2, one module each: preprocess (source selection), initial_guess, gicp (coarse and
fine), semantic_label_filter (on GICP's pairs), dynamic_object_filter, voxel_pfilter (the p-index; its map is
voxel_map). local_map cuts the map around a frame; kernels/ holds the compiled loops, split by the same concepts."""
