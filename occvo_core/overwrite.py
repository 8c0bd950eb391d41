"""Which existing file a writer may replace: one occvo wrote (told by its content), an empty one, or any with --force.
A mistyped `--mcap notes.txt` or `--out ~/.bashrc` is refused instead of silently overwritten.

What counts as occvo's, by kind:
  mcap        an MCAP file whose first record after the header is occvo's metadata record (FoxgloveView writes it)
  rrd         a rerun recording (RRF magic) whose recording names an occvo application (occvo, occvo-<stream>)
  trajectory  a KITTI or TUM trajectory: every line 12 or 8 numbers (what `replay --out`, `store export` write)
  npy         a NumPy array of (M, 4) float64 rows (x, y, z, label: what `occvo tile --out` writes)
"""

from __future__ import annotations

from pathlib import Path

from occvo_core.errors import ConfigError

MCAP_MAGIC = b"\x89MCAP0\r\n"
MCAP_METADATA = "occvo"  # the name of the metadata record FoxgloveView writes first
HEAD_BYTES = 65536  # what is read to tell a file: its start (a big file is never read whole)


def check_replaceable(path: str | Path | None, kind: str, flag: str, force: bool = False) -> None:
    """ConfigError naming `flag` unless `path` is absent, empty, a `kind` file occvo wrote, or `force` is given."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{flag} {path}: is a folder, not a file: name a file")
    if not path.exists() or force:
        return
    try:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot be read to tell whether occvo wrote it: {exc.strerror}") from None
    if head and not RECOGNISERS[kind](head):
        raise ConfigError(
            f"{flag} {path}: exists and is not {DESCRIPTIONS[kind]} occvo wrote: name another file, remove it, or "
            "pass --force to replace it"
        )


def _mcap(head: bytes) -> bool:
    if not head.startswith(MCAP_MAGIC) or head[len(MCAP_MAGIC) : len(MCAP_MAGIC) + 1] != b"\x01":
        return False
    i = len(MCAP_MAGIC) + 9 + int.from_bytes(head[len(MCAP_MAGIC) + 1 : len(MCAP_MAGIC) + 9], "little")
    if head[i : i + 1] != b"\x0c":  # a Metadata record: opcode, length (8), name (4-byte length, bytes)
        return False
    n = int.from_bytes(head[i + 9 : i + 13], "little")
    return head[i + 13 : i + 13 + n] == MCAP_METADATA.encode()


def _rrd(head: bytes) -> bool:
    return head.startswith(b"RRF") and b"occvo" in head[:4096]  # the recording's store info names its application


def _trajectory(head: bytes) -> bool:
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    lines = text.splitlines()
    if len(head) == HEAD_BYTES:
        lines = lines[:-1]  # the last line read may be cut
    rows = [line.split() for line in lines if line.strip()]
    return bool(rows) and all(len(r) in (8, 12) and all(_number(v) for v in r) for r in rows)


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _npy(head: bytes) -> bool:
    import io

    import numpy as np

    try:
        f = io.BytesIO(head)
        fmt = np.lib.format
        read = fmt.read_array_header_1_0 if fmt.read_magic(f) == (1, 0) else fmt.read_array_header_2_0
        shape, _, dtype = read(f)
    except (ValueError, EOFError):
        return False
    return dtype == np.dtype("<f8") and len(shape) == 2 and shape[1] == 4


RECOGNISERS = {"mcap": _mcap, "rrd": _rrd, "trajectory": _trajectory, "npy": _npy}
DESCRIPTIONS = {
    "mcap": "an MCAP file",
    "rrd": "a rerun recording",
    "trajectory": "a KITTI or TUM trajectory",
    "npy": "a tile's .npy array",
}
