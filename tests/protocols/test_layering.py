"""protocols/ is sans-IO: it may import only the standard library, numpy and itself."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FORBIDDEN_STDLIB = {"socket", "threading", "asyncio", "time", "subprocess", "select",
                    "selectors", "multiprocessing"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            mods.add(node.module.split(".")[0])
    return mods


def test_protocols_imports_only_stdlib_and_numpy() -> None:
    files = sorted((ROOT / "protocols").rglob("*.py"))
    assert files
    allowed = set(sys.stdlib_module_names) - FORBIDDEN_STDLIB | {"numpy", "protocols",
                                                                 "__future__"}
    for f in files:
        bad = _imports(f) - allowed
        assert not bad, f"{f.relative_to(ROOT)} imports {sorted(bad)}"


def test_layering_check_catches_a_forbidden_import(tmp_path: Path) -> None:
    f = tmp_path / "x.py"
    f.write_text("import socket\nfrom can import Bus\n")
    assert _imports(f) == {"socket", "can"}
