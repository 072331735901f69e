"""The layout's rules, checked on the source: light device interfaces, small modules, no
function written twice, no issue numbers in code."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("controller", "drivers", "models")
MAX_MODULE_LINES = 600
LONG_MODULES_ALLOWED = {"drivers/sim/ur_emulator.py"}  # one protocol emulator, kept whole
MIN_DUPLICATE_STATEMENTS = 3


def _modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (REPO / package).rglob("*.py"))


def _imported_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sorted(sys.modules)))"
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
    )
    return set(result.stdout.split())


@pytest.mark.parametrize(
    ("statement", "heavy"),
    [
        ("import drivers.base", {"trimesh", "torch", "zenoh"}),
        ("import controller.perception.protocol", {"zenoh"}),
        ("import controller.request", {"zenoh", "torch"}),
        # `touchshape serve` fails fast on a bad endpoint: its parser must not load torch.
        ("import controller.cli.main as m; m.build_parser()", {"torch"}),
    ],
)
def test_interfaces_import_no_heavy_libraries(statement: str, heavy: set[str]) -> None:
    assert not heavy & _imported_after(statement)


def test_no_module_is_over_the_line_limit() -> None:
    long = {
        str(p.relative_to(REPO)): n
        for p in _modules()
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert set(long) <= LONG_MODULES_ALLOWED, long


def _body_key(node: ast.FunctionDef | ast.AsyncFunctionDef) -> str | None:
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]  # the docstring
    statements = sum(isinstance(n, ast.stmt) for s in body for n in ast.walk(s))
    if statements < MIN_DUPLICATE_STATEMENTS:
        return None
    return ast.dump(node.args) + "".join(ast.dump(s) for s in body)


def test_no_two_functions_share_a_body() -> None:
    places: dict[str, list[str]] = defaultdict(list)
    for path in _modules():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                key = _body_key(node)
                if key is not None:
                    places[key].append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}")
    duplicates = [where for where in places.values() if len(where) > 1]
    assert not duplicates, duplicates


def test_code_cites_no_issue_numbers() -> None:
    pattern = re.compile(r"\bissues? ?#?\d|\(#\d+\)|\bitems? \d", re.IGNORECASE)
    cited = [
        f"{path.relative_to(REPO)}:{number}"
        for path in _modules()
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line) and "github.com" not in line and "rerun-io/" not in line
    ]
    assert not cited, cited


def test_the_duplicate_check_finds_a_copy(tmp_path: Path) -> None:
    source = "def a(x):\n    y = x + 1\n    z = y * 2\n    return z\n"
    tree = ast.parse(source + source.replace("def a", "def b"))
    keys = [_body_key(n) for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert keys[0] is not None and keys[0] == keys[1]


def test_dependencies_point_one_way() -> None:
    """controller -> drivers -> models: no module imports from a layer above its own."""
    above = {"controller": set(), "drivers": {"controller"}, "models": {"controller", "drivers"}}
    upward = []
    for path in _modules():
        layer = path.relative_to(REPO).parts[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            else:
                continue
            upward += [
                f"{path.relative_to(REPO)}: {n}" for n in names if n.split(".")[0] in above[layer]
            ]
    assert not upward, upward
