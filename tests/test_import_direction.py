"""Imports point one way (docs/ARCHITECTURE.md, "Folders and imports"): the core, then the stages, then the top
layer (CLI, demo, test support, benchmarks); inside the core, each module or subpackage only below its own tier;
of the tests, only a benchmark's own (in a `bench/` folder) import the benchmarks; and the web player's parts."""

import ast
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STAGES = {"stgs/packager": "stgs.packager", "stgs/server": "stgs.server", "stgs/client": "stgs.client",
          "stgs/harness": "stgs.harness"}
TOP = {"stgs/cli": "stgs.cli", "stgs/testing": "stgs.testing"}
ALLOWED = {"stgs.harness": {"stgs.client"}}
"""Stage -> other stages it may import (the harness drives the reference client)."""


def imported_modules(folder: Path, root: Path = ROOT) -> dict[str, set[str]]:
    """File (relative to root) -> every module it imports, at any depth of the file."""
    out = {}
    for path in sorted(folder.rglob("*.py")):
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module)
        out[str(path.relative_to(root))] = names
    return out


def under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def core_files() -> dict[str, set[str]]:
    """imported_modules of the core: stgs/ without the stages and the top layer."""
    outside = tuple(f"{folder}/" for folder in [*STAGES, *TOP])
    return {f: mods for f, mods in imported_modules(ROOT / "stgs").items() if not f.startswith(outside)}


def test_core_imports_no_stage_and_no_top_layer():
    forbidden = [*STAGES.values(), *TOP.values(), "bench", "tests"]
    bad = {f: sorted(m for m in mods if any(under(m, p) for p in forbidden)) for f, mods in core_files().items()}
    assert not {f: m for f, m in bad.items() if m}


@pytest.mark.parametrize("folder", sorted(STAGES))
def test_stages_import_core_only(folder):
    own = STAGES[folder]
    others = [p for p in [*STAGES.values(), *TOP.values(), "bench", "tests"]
              if p != own and p not in ALLOWED.get(own, ())]
    bad = {f: sorted(m for m in mods if any(under(m, p) for p in others))
           for f, mods in imported_modules(ROOT / folder).items()}
    assert not {f: m for f, m in bad.items() if m}


def test_top_layer_imports_no_benchmark_and_no_test():
    bad = {f: sorted(m for m in mods if under(m, "bench") or under(m, "tests"))
           for folder in TOP for f, mods in imported_modules(ROOT / folder).items()}
    assert not {f: m for f, m in bad.items() if m}


def test_only_a_benchmarks_own_tests_import_it():
    """A test of a benchmark's code sits in a `bench/` folder under the tests of what it measures; every other test
    imports the library and test support only, and the benchmarks import no test."""
    bad = {f: sorted(m for m in mods if under(m, "bench"))
           for f, mods in imported_modules(ROOT / "tests").items() if "bench" not in Path(f).parts[:-1]}
    assert not {f: m for f, m in bad.items() if m}
    from_bench = {f: sorted(m for m in mods if under(m, "tests"))
                  for f, mods in imported_modules(ROOT / "bench").items()}
    assert not {f: m for f, m in from_bench.items() if m}


def test_checker_sees_an_import_inside_a_function(tmp_path):
    (tmp_path / "x.py").write_text("def f():\n    from stgs.server.app import build_app\n")
    assert "stgs.server.app" in imported_modules(tmp_path, tmp_path)["x.py"]


CORE_TIERS = (
    {"errors", "limits", "lazy", "fsio", "memory", "picks", "loopback"},
    {"native", "tasks", "tree"},
    {"render", "metrics"},
    {"camera"},
    {"model"},
    {"codec"},
    {"mpd"},
    {"packaged"},
    {"interop"},
    {"synth"},
    {"data"},
    {"prepare", "train"},
    {"evaluate"},
)
"""The core's own modules and subpackages (`stgs.<name>`), lowest first: each imports only from tiers below its own
(docs/ARCHITECTURE.md, "Folders and imports", draws the same order)."""


def core_imports() -> dict[str, set[str]]:
    """`stgs.<name>` -> the other `stgs.<name>` it imports (any depth of either)."""
    out: dict[str, set[str]] = {}
    for path, mods in core_files().items():
        parts = Path(path).with_suffix("").parts
        if parts[1:] == ("__init__",):
            continue
        own = parts[1]
        out.setdefault(own, set()).update(
            m.split(".")[1] for m in mods if under(m, "stgs") and m.count(".") >= 1 and m.split(".")[1] != own
            and not any(under(m, p) for p in [*STAGES.values(), *TOP.values()]))
    return out


def upward_imports() -> list[str]:
    """Each import of the core that is not to a lower tier of CORE_TIERS (an untiered module counts as the top)."""
    tier = {name: i for i, names in enumerate(CORE_TIERS) for name in names}
    graph = core_imports()
    return sorted(f"stgs.{a} -> stgs.{b}" for a, deps in graph.items() for b in deps
                  if tier.get(b, len(CORE_TIERS)) >= tier.get(a, len(CORE_TIERS)))


def test_the_core_imports_downwards_only():
    assert sorted(set(core_imports()) - set().union(*CORE_TIERS)) == []  # a new module takes a place in CORE_TIERS
    assert upward_imports() == []


def package_imports() -> dict[str, set[str]]:
    """`stgs.<name>` -> the other `stgs.<name>` it imports, over the whole package (core, stages, top layer)."""
    out: dict[str, set[str]] = {}
    for path, mods in imported_modules(ROOT / "stgs", ROOT).items():
        parts = Path(path).with_suffix("").parts
        if parts[1:] == ("__init__",):
            continue
        own = parts[1]
        out.setdefault(own, set()).update(m.split(".")[1] for m in mods
                                          if under(m, "stgs") and m.count(".") >= 1 and m.split(".")[1] != own)
    return out


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every cycle of `graph`, as its strongly connected components of more than one node (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while (top := stack.pop()) != node:
                component.append(top)
            if component:
                found.append(sorted([node, *component]))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def test_the_package_has_no_import_cycle():
    assert import_cycles(package_imports()) == []


def test_the_cycle_finder_finds_the_cycle_the_package_once_had():
    graph = {"data": {"synth", "camera"}, "synth": {"interop"}, "interop": {"evaluate"}, "evaluate": {"train"},
             "train": {"data", "model"}, "model": set(), "camera": set()}
    assert import_cycles(graph) == [["data", "evaluate", "interop", "synth", "train"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


# python -m tests.test_import_direction: the import graph of stgs's subpackages, its cycles, and the core's imports
# that go against the tiers
if __name__ == "__main__":
    graph = package_imports()
    for module, deps in sorted(graph.items()):
        print(f"stgs.{module} -> {', '.join(f'stgs.{d}' for d in sorted(deps)) or '(nothing)'}")
    print("cycles:", "; ".join(" -> ".join(f"stgs.{m}" for m in c) for c in import_cycles(graph)) or "none")
    print("upward:", ", ".join(upward_imports()) or "none")


WEB_SRC = ROOT / "web" / "src"
WEB_FORBIDDEN = {
    "stream": ("render/", "player", "ui", "main"),
    "render": ("stream/", "player", "ui", "main"),
    "abr": ("stream/", "render/", "player", "ui", "main"),
    "workers": ("stream/", "render/", "player", "ui", "main"),
    "camera": ("stream/", "render/", "player", "ui", "main"),
}
"""The web player's parts and what each may not import (docs/ARCHITECTURE.md, "Folders and imports"): streaming
and rendering know nothing of each other, and only the player and the page join them."""


def web_imports(path: Path) -> set[str]:
    """The web/src-relative modules a TypeScript file imports (relative specifiers only)."""
    found = set()
    for spec in re.findall(r'^\s*(?:import|export)[^;]*?from\s+"(\.[^"]+)"', path.read_text(), re.M | re.S):
        found.add((path.parent / spec).resolve().relative_to(WEB_SRC.resolve()).as_posix())
    return found


@pytest.mark.skipif(not WEB_SRC.is_dir(), reason="no web/src")
def test_the_web_players_parts_import_one_way():
    bad = {}
    for path in sorted(WEB_SRC.rglob("*.ts")):
        rel = path.relative_to(WEB_SRC).as_posix()
        part = rel.split("/")[0] if "/" in rel else rel.removesuffix(".ts")
        banned = WEB_FORBIDDEN.get(part, ())
        hits = sorted(m for m in web_imports(path) if any(m == b or m.startswith(b) for b in banned))
        if hits:
            bad[rel] = hits
    assert bad == {}


def test_the_web_check_sees_an_import_it_forbids(tmp_path, monkeypatch):
    (tmp_path / "render").mkdir()
    (tmp_path / "render" / "x.ts").write_text('import { a } from "../stream/y";\nimport type { B } from "./z";\n')
    monkeypatch.setattr(sys.modules[__name__], "WEB_SRC", tmp_path)
    assert web_imports(tmp_path / "render" / "x.ts") == {"stream/y", "render/z"}
