"""What SQLite and PostgreSQL spell differently in the store's SQL, so that every query and write is written once:
statements use `?` for a parameter and {words} below, and a dialect renders them for its database.

SQLite keeps lease times as seconds since the epoch by this host's clock (a SQLite file has one host); PostgreSQL
as timestamps by the server's clock (now()), so that the hosts' clocks do not matter."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

_SQLITE_NOW = "((julianday('now') - 2440587.5) * 86400.0)"


@dataclass(frozen=True)
class Dialect:
    name: str
    param: str
    words: dict[str, str] = field(hash=False, compare=False)

    def sql(self, template: str) -> str:
        """The statement in this dialect (rendered once a template)."""
        return _render(self, template)


@functools.lru_cache(maxsize=512)
def _render(dialect: Dialect, template: str) -> str:
    return template.format(**dialect.words).replace("?", dialect.param)


SQLITE = Dialect(
    "sqlite",
    "?",
    {
        "now": _SQLITE_NOW,
        "later": f"({_SQLITE_NOW} + ?)",  # now plus ? seconds
        "remaining": f"(expires_at - {_SQLITE_NOW})",  # seconds until a lease expires
        "distinct": "IS NOT",
        "for_share": "",  # one writer a file: a write transaction holds every row it read
        "for_update": "",
    },
)
POSTGRES = Dialect(
    "postgresql",
    "%s",
    {
        "now": "now()",
        "later": "(now() + make_interval(secs => ?))",
        "remaining": "EXTRACT(EPOCH FROM expires_at - now())",
        "distinct": "IS DISTINCT FROM",
        "for_share": " FOR SHARE",  # the lease row held against a takeover until the write commits
        "for_update": " FOR UPDATE",
    },
)
