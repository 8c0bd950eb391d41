"""The registration worker's and the map service's durable state, whichever database holds it.

  records, errors   what the store hands back and raises (StoredPose, StreamRecord, Lease; StoreUnavailable, FencedError)
  protocols         what it answers, by concern: FrameLog, Snapshots, ColdTiles, Leases, Usage, Housekeeping, MapTiles
  factory           open_store, open_map_store, check_store (before any worker starts): the one door to a database
  url, blobs        the store URL and its secrets; the frames' blobs and digests
  frame_log, snapshots, cold_tiles, leases, usage
                    the parts, their SQL written once for both databases (dialect)
  sqlite*, pg_*     the two databases' stores built from those parts, their files, connections and snapshots
  map_tiles*        the map service's tiles

The registration worker imports records, errors, protocols, url, blobs and factory only (tests/service/
test_store_edges.py)."""
