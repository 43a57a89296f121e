"""Dependencies point one way (DESIGN.md, Folders): core <- stages <- top layer (CLI, demo, benchmarks)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STAGES = {"packager": "stgs.packager", "server": "stgs.server", "client": "stgs.client", "harness": "stgs.harness"}
TOP = {"cli": "stgs.cli"}
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


def test_core_imports_no_stage_and_no_top_layer():
    forbidden = [*STAGES.values(), *TOP.values(), "bench"]
    bad = {f: sorted(m for m in mods if any(under(m, p) for p in forbidden))
           for f, mods in imported_modules(ROOT / "stgs").items()}
    assert not {f: m for f, m in bad.items() if m}


@pytest.mark.parametrize("folder", sorted(STAGES))
def test_stages_import_core_only(folder):
    own = STAGES[folder]
    others = [p for p in [*STAGES.values(), *TOP.values(), "bench"] if p != own and p not in ALLOWED.get(own, ())]
    bad = {f: sorted(m for m in mods if any(under(m, p) for p in others))
           for f, mods in imported_modules(ROOT / folder).items()}
    assert not {f: m for f, m in bad.items() if m}


def test_checker_sees_an_import_inside_a_function(tmp_path):
    (tmp_path / "x.py").write_text("def f():\n    from stgs.server.app import build_app\n")
    assert "stgs.server.app" in imported_modules(tmp_path, tmp_path)["x.py"]


CORE_TIERS = (
    {"errors", "limits", "lazy", "fsio", "memory", "picks", "loopback", "mpd_schema"},
    {"native", "mpd_values", "tasks"},
    {"render", "metrics"},
    {"tree", "mpd"},
    {"camera"},
    {"model"},
    {"codec"},
    {"mpd_profile"},
    {"packaged"},
    {"interop"},
    {"synth"},
    {"data"},
    {"prepare", "train"},
    {"evaluate"},
)
"""The core's own modules and subpackages (`stgs.<name>`), lowest first: each imports only from tiers below its own
(docs/ARCHITECTURE.md once it exists; until then the order is this list)."""


def core_imports() -> dict[str, set[str]]:
    """`stgs.<name>` -> the other `stgs.<name>` it imports (any depth of either)."""
    out: dict[str, set[str]] = {}
    for path, mods in imported_modules(ROOT / "stgs").items():
        parts = Path(path).with_suffix("").parts
        if parts[1:] == ("__init__",):
            continue
        own = parts[1]
        out.setdefault(own, set()).update(
            m.split(".")[1] for m in mods if under(m, "stgs") and m.count(".") >= 1 and m.split(".")[1] != own
            and not any(under(m, p) for p in [*STAGES.values(), *TOP.values()]))
    return out


def test_the_core_imports_downwards_only():
    tier = {name: i for i, names in enumerate(CORE_TIERS) for name in names}
    graph = core_imports()
    assert sorted(set(graph) - set(tier)) == []  # a new module or subpackage takes a place in CORE_TIERS
    upward = sorted(f"stgs.{a} -> stgs.{b}" for a, deps in graph.items() for b in deps if tier[b] >= tier[a])
    assert upward == []
