"""The store's two errors, whichever database holds it."""

from __future__ import annotations


class StoreUnavailable(RuntimeError):
    """The store's database cannot be reached; the next call connects again."""


class FencedError(RuntimeError):
    """A write under an epoch the stream's lease no longer has: another worker owns the stream now."""

    def __init__(self, stream: str, epoch: int | None, current: int | None, owner: str | None = None):
        self.stream, self.epoch, self.current, self.owner = stream, epoch, current, owner
        now = "no lease" if current is None else f"epoch {current}" + (f" (owner {owner})" if owner else "")
        under = (
            "without a lease (every write of this store is fenced)" if epoch is None else f"under lease epoch {epoch}"
        )
        super().__init__(f"stream {stream}: write {under} refused, the lease is at {now}")
