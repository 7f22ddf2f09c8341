"""The package's import graph, read with ast (nothing imported; top-level and function-local
imports alike): the layers' arrow rule of docs/design.md (a module imports its own layer or the
layers below, never one above), no circle among the modules of any layer, and no module taking a
name of another module that is private (a leading underscore) or, across packages, missing from
the ``__all__`` of the package holding it."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The layers, bottom to top (docs/design.md, "Data flow and layers").
LAYERS = ("qr_cl.runtime", "qr_cl.scene", "qr_cl.stages", "qr_cl.render", "qr_cl.backbone", "qr_cl.app")
#: The one part of the app that reaches past render/ to the stages: the kernel benchmark, which
#: times each stage alone (and launches bare kernels for the device's limits). Every other app
#: path renders through render/ (docs/design.md, "One rendering path").
STAGE_BENCHMARK = "qr_cl.app.bench"
#: Where each package's sources lie (qr_cl.backbone is installed from backbone/, setup.cfg).
SOURCES = {"qr_cl": ROOT / "qr_cl", "qr_cl.backbone": ROOT / "backbone"}


def modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package as its ``__init__``)."""
    found = {}
    for prefix, folder in SOURCES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join([prefix, *parts])] = path
    return found


def is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def declared_all(path: Path) -> list[str] | None:
    """The literal ``__all__`` of a module, or None when it has none."""
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return list(ast.literal_eval(node.value))
    return None


def imports(name: str, path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, absolute module, names) of every ``from ... import`` and ``import`` in the module
    ``name``, at any depth (function-local ones too)."""
    package = name if is_package(path) else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package
            for _ in range(node.level - 1):
                base = base.rpartition(".")[0]
            target = node.module or "" if not node.level else ".".join(p for p in (base, node.module) if p)
            out.append((node.lineno, target, [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            out += [(node.lineno, alias.name, []) for alias in node.names]
    return out


def edges(mods: dict[str, Path], within: str) -> dict[str, set[str]]:
    """The modules under ``within`` each module under it imports (a ``from pkg import module``
    counts as importing that module)."""
    graph: dict[str, set[str]] = {m: set() for m in mods if m.startswith(within + ".")}
    for m in graph:
        for _, target, names in imports(m, mods[m]):
            for t in [target, *(f"{target}.{n}" for n in names)]:
                if t in graph and t != m:
                    graph[m].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """A circle through each module that lies on one (depth-first search)."""
    found, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                found.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return found


def private_imports(mods: dict[str, Path], importers: dict[str, Path]) -> list[str]:
    """``file:line name from module`` of each import of a private or unexported name."""
    bad = []
    for m, path in importers.items():
        own_package = m if is_package(path) else m.rpartition(".")[0]
        for line, target, names in imports(m, path):
            if target not in mods:
                continue
            holder = target if is_package(mods[target]) else target.rpartition(".")[0]
            exported = declared_all(mods[holder]) if holder in mods and holder != own_package else None
            for n in names:
                if f"{target}.{n}" in mods:                # a module, not a name in one
                    continue
                if n.startswith("_") or (exported is not None and n not in exported):
                    bad.append(f"{path.relative_to(ROOT)}:{line} {n} from {target}")
    return bad


def stage_imports(mods: dict[str, Path]) -> list[tuple[str, int, str]]:
    """(importer, line, module) of each import of qr_cl.stages by a module of the app outside
    :data:`STAGE_BENCHMARK`."""
    bad = []
    for m, path in mods.items():
        if not m.startswith("qr_cl.app.") or m.startswith(STAGE_BENCHMARK + "."):
            continue
        bad += [(m, line, target) for line, target, _ in imports(m, path)
                if target == "qr_cl.stages" or target.startswith("qr_cl.stages.")]
    return bad


def layer(module: str) -> int | None:
    """The position in :data:`LAYERS` of the layer holding ``module`` (None: the top package)."""
    return next((i for i, name in enumerate(LAYERS) if module == name or module.startswith(name + ".")), None)


def upward_imports(mods: dict[str, Path]) -> list[tuple[str, int, str]]:
    """(importer, line, module) of each import of a module of a higher layer than the importer's."""
    bad = []
    for m, path in mods.items():
        for line, target, names in imports(m, path):
            for t in [target, *(f"{target}.{n}" for n in names)]:
                if t in mods and layer(m) is not None and (layer(t) or 0) > layer(m):
                    bad.append((m, line, t))
    return bad


def listing(found: list[tuple[str, int, str]]) -> str:
    """(importer, line, module) rows, one per line, for an assertion's message."""
    return "\n  " + "\n  ".join(f"{m}:{line} {t}" for m, line, t in found)


def test_every_module_is_in_a_layer():
    assert [m for m in modules() if layer(m) is None] == ["qr_cl"]


def test_no_layer_imports_a_layer_above_it():
    bad = upward_imports(modules())
    assert not bad, "imports of a higher layer:" + listing(bad)


def test_the_arrow_rule_catches_an_upward_import(tmp_path):
    module = tmp_path / "upward.py"
    module.write_text("def f():\n    from ..render import rasterize\n")
    found = upward_imports({**modules(), "qr_cl.scene.upward": module})
    assert found == [("qr_cl.scene.upward", 2, "qr_cl.render"), ("qr_cl.scene.upward", 2, "qr_cl.render.rasterize")]


def test_the_app_renders_through_render_only():
    bad = stage_imports(modules())
    assert not bad, "app modules importing the stages:" + listing(bad)


def test_the_stage_rule_catches_an_app_module_taking_a_stage(tmp_path):
    module = tmp_path / "shortcut.py"
    module.write_text("from ...stages import select\n")
    assert stage_imports({**modules(), "qr_cl.app.training.shortcut": module}) == [
        ("qr_cl.app.training.shortcut", 1, "qr_cl.stages")]
    assert stage_imports({**modules(), "qr_cl.app.bench.shortcut": module}) == []


@pytest.mark.parametrize("package", LAYERS)
def test_no_import_circle_in_a_layer(package):
    found = cycles(edges(modules(), package))
    assert not found, f"import circles in {package}: " + "; ".join(" -> ".join(c) for c in found)


def test_modules_import_only_public_names():
    mods = modules()
    bench = {f"bench.{p.stem}": p for p in sorted((ROOT / "bench").glob("*.py"))}
    bad = private_imports(mods, {**mods, **bench})
    assert not bad, "private or unexported names imported across modules:\n  " + "\n  ".join(bad)
