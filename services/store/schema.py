"""The store's tables in each database: the column types are the dialect's (the queries and writes, written once,
are in the parts). SQLite keeps the snapshots in a file of their own (services/store/sqlite_files.py).

  streams     stream, created, last_seq (last committed frame), snapshot_seq, client, bytes, last_write
  poses       (stream, seq): stamp, digest of the frame, status, pose (4x4 float64 bytes); every published pose
  snapshots   stream: the trajectory's `created`, seq, the lease epoch it was written under, the OccVO state_dict
              after that frame (working map only); the latest one per stream
  journal     (stream, seq): the occupancy frames registered after the snapshot, to replay on resume
  cold_tiles  (stream, ix, iy, evicted_seq): map tiles evicted from the working set, with restored_seq once they came
              back. A restored row stays until the next snapshot: resuming from an older snapshot replays the frames
              that restored it and needs the block as it was.
  leases      stream: owner, fencing epoch, expires_at
"""

from __future__ import annotations

SQLITE_FRAMES = """
CREATE TABLE IF NOT EXISTS streams (
    stream       TEXT PRIMARY KEY,
    created      REAL NOT NULL,
    last_seq     INTEGER,
    snapshot_seq INTEGER,
    client       TEXT,  -- retention (services/store/usage.py): who wrote it last, its bytes, its last frame
    bytes        INTEGER NOT NULL DEFAULT 0,
    last_write   REAL
);
CREATE TABLE IF NOT EXISTS poses (
    stream TEXT NOT NULL,
    seq    INTEGER NOT NULL,
    stamp  REAL NOT NULL,
    digest BLOB NOT NULL,
    status TEXT NOT NULL,
    pose   BLOB NOT NULL,
    PRIMARY KEY (stream, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS journal (
    stream TEXT NOT NULL,
    seq    INTEGER NOT NULL,
    frame  BLOB NOT NULL,
    PRIMARY KEY (stream, seq)
);
CREATE TABLE IF NOT EXISTS cold_tiles (
    stream       TEXT NOT NULL,
    ix           INTEGER NOT NULL,
    iy           INTEGER NOT NULL,
    evicted_seq  INTEGER NOT NULL,
    restored_seq INTEGER,
    block        BLOB NOT NULL,
    PRIMARY KEY (stream, ix, iy, evicted_seq)
);
CREATE TABLE IF NOT EXISTS leases (
    stream     TEXT PRIMARY KEY,
    owner      TEXT,
    epoch      INTEGER NOT NULL,
    expires_at REAL NOT NULL
);
"""

SQLITE_SNAPSHOTS = """
CREATE TABLE IF NOT EXISTS snapshots (
    stream  TEXT PRIMARY KEY,
    created REAL NOT NULL,
    seq     INTEGER NOT NULL,
    state   BLOB NOT NULL,
    epoch   INTEGER  -- the lease epoch it was written under (NULL: unfenced); a later epoch's is never replaced
);
"""

# blobs are stored as they are (STORAGE EXTERNAL): compressing a frame or a snapshot costs CPU in the commit's path
POSTGRES = """
CREATE TABLE IF NOT EXISTS streams (
    stream       TEXT PRIMARY KEY,
    created      DOUBLE PRECISION NOT NULL,
    last_seq     BIGINT,
    snapshot_seq BIGINT
);
CREATE TABLE IF NOT EXISTS poses (
    stream TEXT NOT NULL,
    seq    BIGINT NOT NULL,
    stamp  DOUBLE PRECISION NOT NULL,
    digest BYTEA NOT NULL,
    status TEXT NOT NULL,
    pose   BYTEA NOT NULL,
    PRIMARY KEY (stream, seq)
);
CREATE TABLE IF NOT EXISTS journal (
    stream TEXT NOT NULL,
    seq    BIGINT NOT NULL,
    frame  BYTEA NOT NULL,
    PRIMARY KEY (stream, seq)
);
ALTER TABLE journal ALTER COLUMN frame SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS cold_tiles (
    stream       TEXT NOT NULL,
    ix           INTEGER NOT NULL,
    iy           INTEGER NOT NULL,
    evicted_seq  BIGINT NOT NULL,
    restored_seq BIGINT,
    block        BYTEA NOT NULL,
    PRIMARY KEY (stream, ix, iy, evicted_seq)
);
ALTER TABLE cold_tiles ALTER COLUMN block SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS snapshots (
    stream  TEXT PRIMARY KEY,
    created DOUBLE PRECISION NOT NULL,
    seq     BIGINT NOT NULL,
    epoch   BIGINT,
    state   BYTEA NOT NULL
);
ALTER TABLE snapshots ALTER COLUMN state SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS leases (
    stream     TEXT PRIMARY KEY,
    owner      TEXT,
    epoch      BIGINT NOT NULL,
    expires_at TIMESTAMPTZ NOT NULL
);
-- the retention columns, only when missing: an ALTER or CREATE INDEX on `streams` locks it, and opening a store beside
-- running writers then deadlocked with them (the earlier statements hold the journal's lock)
DO $$ BEGIN
    IF NOT EXISTS (SELECT 1 FROM information_schema.columns WHERE table_schema = current_schema()
                   AND table_name = 'streams' AND column_name = 'last_write') THEN
        ALTER TABLE streams ADD COLUMN IF NOT EXISTS client TEXT,
            ADD COLUMN IF NOT EXISTS bytes BIGINT NOT NULL DEFAULT 0, ADD COLUMN IF NOT EXISTS last_write DOUBLE PRECISION;
        CREATE INDEX IF NOT EXISTS streams_client ON streams (client);
    END IF;
END $$;
"""
