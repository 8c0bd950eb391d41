"""occvo_core holds the algorithms and no transport: none of its modules imports zenoh or the service's packages."""

from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "occvo_core"
TRANSPORT = ("zenoh", "occvo_services", "occvo_schemas", "services", "schemas")


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def test_occvo_core_imports_no_transport():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) > 50  # the whole package was read
    found = {
        f"{path.relative_to(CORE.parent)}: {name}"
        for path in files
        for name in _imports(path)
        if name.split(".")[0] in TRANSPORT
    }
    assert not found, found


def test_the_check_sees_an_import_of_the_transport(tmp_path):
    sample = tmp_path / "m.py"
    sample.write_text("def f():\n    import zenoh\n    from occvo_schemas.codec import decode\n")
    assert _imports(sample) == {"zenoh", "occvo_schemas.codec"}
