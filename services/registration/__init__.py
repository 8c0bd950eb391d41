"""The registration worker: occupancy frames in, OccVO per stream, poses out in sequence order, map tile updates out.

Map updates: after each frame the worker cuts again the map tiles the frame changed (OccVO.pop_changed_region,
occvo_core.map_tiles.retile_region) and publishes only the tiles whose content changed (a tile that emptied is sent
empty), so the map service always equals the odometry's map; the cost follows the changed area, not the map's size.

A frame's pose goes out as soon as it is registered (OccVO.register: through fine GICP); the loop-closure search, the
map update, eviction and restores follow off its latency (OccVO.complete and _finish). A frame that closed a loop
then publishes its relocalised pose (status "relocalised"), which replaces the first.

Durable state (`store_path`, services/store/): every pose is committed with its frame before it is published, the
OccVO state is snapshotted every `snapshot_every` frames (less often when snapshots would take more than
`snapshot_max_share` of the stream's time, the first one too) and at shutdown; a restarted worker resumes a stream at its
next frame from the snapshot plus the journaled frames. The lane only copies the state; one writer thread writes the
copies into the store's snapshot file, so neither this stream's next frame nor another stream's commit waits for it.
A resent frame already registered gets its stored pose again.
With `working_radius_m`, map tiles wholly farther than that from the ego leave the working set for the store (the map
service keeps serving them) and come back when the ego is within working_radius_m - tile_m of them.
"""
