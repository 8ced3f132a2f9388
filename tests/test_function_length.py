"""No function in the package is longer than `MAX_LINES` (issue #31): a long one is split by job into
well-named private functions or small dataclasses."""

from __future__ import annotations

import ast
from pathlib import Path

import torch_diffavatar

MAX_LINES = 80  # `def` line to last line, docstring included
PACKAGE = Path(torch_diffavatar.__file__).parent
NOT_YET: tuple[str, ...] = ()  # files or folders ("sim/") still being split
# the fit driver stays thin: the objective, logging, report and race live elsewhere
MAX_FITTER_LINES = 300


def _long_functions(root: Path, max_lines: int, skip: tuple[str, ...] = ()) -> list[str]:
    """'path:line name (n lines)' of every function or method under ``root`` longer than ``max_lines``,
    except in the files (relative paths) or folders (ending in "/") of ``skip``."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel in skip or any(s.endswith("/") and rel.startswith(s) for s in skip):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                count = node.end_lineno - node.lineno + 1
                if count > max_lines:
                    out.append(f"{rel}:{node.lineno} {node.name} ({count} lines)")
    return out


def test_no_function_is_over_80_lines():
    assert _long_functions(PACKAGE, MAX_LINES, NOT_YET) == []


def test_the_fit_driver_is_thin():
    import torch_diffavatar.fit as fit

    (node,) = [
        n for n in ast.parse(Path(fit.__file__).read_text()).body if getattr(n, "name", "") == "Fitter"
    ]
    assert node.end_lineno - node.lineno + 1 < MAX_FITTER_LINES


def test_the_check_finds_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(80))
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "m.py").write_text(f"def short():\n    pass\n\n\ndef long():\n{body}\n")
    (tmp_path / "skipped.py").write_text(f"def long():\n{body}\n")
    assert _long_functions(tmp_path, MAX_LINES, ("skipped.py",)) == ["sub/m.py:5 long (81 lines)"]
    assert _long_functions(tmp_path, MAX_LINES, ("sub/", "skipped.py")) == []
