"""The registration worker reaches its store through the store's protocols only (services/store/protocols.py): none of
its modules imports a database's store (services/store/sqlite*.py, postgres.py, pg_*.py), sqlite3 or psycopg; as
tests/core/test_no_transport.py does for the core. The factory opens the store, the records and errors are what it
hands back and raises, url and blobs are the URL's secrets and the frames' blobs."""

from __future__ import annotations

import ast
from pathlib import Path

SERVICES = Path(__file__).resolve().parents[2] / "services"
STORE = "occvo_services.store"
ALLOWED = {f"{STORE}.{m}" for m in ("records", "errors", "protocols", "factory", "url", "blobs")}


def _imports(path: Path, package: str) -> set[str]:
    """Every module a file imports (relative imports resolved in `package`; `from a import b` also as a.b)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}".rstrip(".")
            names.add(base)
            names.update(f"{base}.{a.name}" for a in node.names)
    return names


def _refused(name: str) -> bool:
    if name.split(".")[0] in ("sqlite3", "psycopg"):
        return True
    if name == STORE or not name.startswith(STORE + "."):
        return False
    return ".".join(name.split(".")[:3]) not in ALLOWED


def test_registration_imports_the_store_through_its_protocols_only():
    files = sorted((SERVICES / "registration").rglob("*.py"))
    assert len(files) > 10  # the whole package was read
    found = {
        f"{path.relative_to(SERVICES)}: {name}"
        for path in files
        for name in _imports(path, "occvo_services.registration")
        if _refused(name)
    }
    assert not found, found
    assert any(f"{STORE}.protocols" in _imports(p, "") or f"{STORE}.factory" in _imports(p, "") for p in files)


def _store_calls(path: Path) -> set[str]:
    """The attributes the code takes of a store: `store.X`, `self.store.X`, `ctx.store.X`..."""
    calls = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Attribute):
            owner = node.value
            name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", "")
            if name == "store":
                calls.add(node.attr)
    return calls


def test_what_registration_calls_of_its_store_the_protocols_name():
    from occvo_services.store.protocols import TRAJECTORY_STORE, calls

    named = {c for protocol in TRAJECTORY_STORE for c in calls(protocol)} | {"fenced_only"}
    used = {c for path in sorted((SERVICES / "registration").rglob("*.py")) for c in _store_calls(path)}
    assert {"commit_frame", "acquire", "write_snapshot", "cold_block", "measure"} <= used  # the calls were found
    assert used <= named, used - named


def test_the_check_sees_a_backend_however_it_is_imported(tmp_path):
    sample = tmp_path / "m.py"
    sample.write_text(
        "import sqlite3\nfrom occvo_services.store import sqlite\nfrom ..store.postgres import PgTrajectoryStore\n"
        "from occvo_services.store.protocols import FrameLog\nfrom occvo_services.store.pg_pool import PgPool\n"
    )
    refused = {n for n in _imports(sample, "occvo_services.registration") if _refused(n)}
    assert refused == {
        "sqlite3",
        "occvo_services.store.sqlite",
        "occvo_services.store.postgres",
        "occvo_services.store.postgres.PgTrajectoryStore",
        "occvo_services.store.pg_pool",
        "occvo_services.store.pg_pool.PgPool",
    }
