"""The services' shape rules (issue 65): no mixin classes, no function over 60 lines, no module over 400 lines."""

from __future__ import annotations

import ast
from pathlib import Path

SERVICES = Path(__file__).resolve().parents[2] / "services"


def test_no_mixins_no_long_functions_no_long_modules():
    found = []
    for path in sorted(SERVICES.rglob("*.py")):
        text, name = path.read_text(), path.relative_to(SERVICES)
        if len(text.splitlines()) > 400:
            found.append(f"{name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and "Mixin" in " ".join([node.name, *map(ast.unparse, node.bases)]):
                found.append(f"{name}:{node.lineno} mixin {node.name}")
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno - node.lineno >= 60:
                found.append(f"{name}:{node.lineno} {node.name}: {node.end_lineno - node.lineno + 1} lines")
    assert found == []
