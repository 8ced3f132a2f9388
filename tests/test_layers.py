"""The package's layers (docs: DESIGN.md, "Modules"): every import goes down, never up or sideways, and
no import cycle exists, function-level imports included."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torch_diffavatar"
NAME = "torch_diffavatar"

# module (or package) -> (layer, group). An import must go to a lower layer, or stay in its own group.
LAYERS = {
    "errors": (0, "base"),
    "_ext": (0, "base"),
    "geometry": (0, "base"),
    "metrics": (0, "base"),
    "render": (0, "base"),
    "chamfer": (0, "base"),
    "json_io": (0, "base"),
    "atomic_file": (0, "base"),
    "forked": (0, "base"),  # calls run in forked worker processes (the body fit's directions, the race)
    "pattern": (1, "pattern"),
    "mesh_io": (2, "io"),
    "scan": (2, "io"),
    "scan_intake": (2, "io"),
    "sim": (2, "sim"),
    "body": (2, "body"),
    "cage": (3, "terms"),  # the pattern's control cage and the loss terms (which use its seam segments)
    "losses": (3, "terms"),
    "opening_lengths": (3, "terms"),  # a hem's length, from the scan's points and from the rest pattern
    "rest_terms": (3, "terms"),  # the rest terms' C++ kernels as one autograd node
    "assets": (3, "assets"),
    "assets_newton": (3, "assets"),  # the asset's material in Newton's units (pure numpy)
    "scan_fit_picture": (3, "assets"),  # the scan on its fit, coloured by distance (render, no fit)
    "motion": (3, "motion"),
    "fit_config": (3, "fit_config"),  # the fit's settings: the objective reads them
    "capture": (3, "capture"),  # simulated depth captures: meshes in, points out (numpy)
    "sim_newton": (3, "sim_newton"),  # Newton's cloth on our sim model: synthetic scans' second physics
    "objective": (4, "objective"),
    "synthetic_scans": (4, "synthetic_scans"),
    "captured_scans": (4, "synthetic_scans"),
    "evaluation": (4, "evaluation"),
    "animate": (4, "animate"),
    "fit": (5, "fit"),
    "batch": (5, "fit"),  # batch fitting's manifest and summary: reads the fit folders it gathers
    "commands": (6, "commands"),
    "cli": (7, "cli"),
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``path`` imports anywhere in its body (``from a import b`` is ``a.b``
    when that is a module)."""
    module = _module_name(path)
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == NAME}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join(anchor + ([base] if base else []))
            if base.split(".")[0] != NAME:
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub == f"{NAME}._C":  # the compiled extension, loaded by `_ext` alone
                    continue
                found.add(sub if sub in modules else base)
    return {m for m in found if m in modules and m != module}


def _area(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _layer(module: str) -> tuple[int, str]:
    area = _area(module)
    if area.startswith("fit_") and area not in LAYERS:  # the fit driver's parts
        area = "fit"
    if area not in LAYERS:
        raise AssertionError(f"{module}: not in the layer table of tests/test_layers.py; add it")
    return LAYERS[area]


def test_every_import_goes_down_a_layer():
    modules = _modules()
    wrong = []
    for module, path in sorted(modules.items()):
        if module == NAME:  # the package root re-exports the public API
            continue
        layer, group = _layer(module)
        for target in sorted(_imports(path, modules)):
            if target == NAME:
                wrong.append(f"{module} -> {target} (the package root)")
                continue
            t_layer, t_group = _layer(target)
            if t_layer > layer or (t_layer == layer and t_group != group):
                wrong.append(f"{module} (layer {layer}, {group}) -> {target} (layer {t_layer}, {t_group})")
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def test_no_import_cycle():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    modules = _modules()
    # a package's __init__ imports its submodules; a submodule importing its package's __init__ back
    # is the cycle to find
    names = sorted(modules)
    index = {m: k for k, m in enumerate(names)}
    edges = [(index[m], index[t]) for m in names for t in _imports(modules[m], modules)]
    if not edges:
        pytest.skip("no imports")
    rows, cols = zip(*edges)
    graph = coo_matrix(([1] * len(edges), (rows, cols)), shape=(len(names), len(names)))
    _, labels = connected_components(graph, directed=True, connection="strong")
    groups: dict[int, list[str]] = {}
    for name, label in zip(names, labels):
        groups.setdefault(label, []).append(name)
    cycles = [g for g in groups.values() if len(g) > 1]
    assert not cycles, f"import cycles: {cycles}"
