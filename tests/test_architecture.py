"""The package layout of docs/ARCHITECTURE.md "Package layout and the allowed imports", enforced.

Every import of the project's own modules is read with ``ast`` (those inside functions
included, as they run just the same), then: the import graph has no circle; each gyrocore
module imports only from its own subpackage and the layers below it; nothing in gyrocore, sim or
the experiments' library modules imports a CLI module; gyrocore never imports sim or mujoco, and
every gyrocore module imports with both made unimportable.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("gyrocore", "sim", "experiments")

#: docs/ARCHITECTURE.md's layers, lowest first: a gyrocore module may import its own unit and
#: the units of lower layers. A unit is a subpackage (``gyrocore.calib``) or a top-level module.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("gyrocore.errors",),
    ("gyrocore.attitude",),
    ("gyrocore.data",),
    ("gyrocore.effects",),
    ("gyrocore.readers",),
    ("gyrocore.flight",),
    ("gyrocore.noise",),
    ("gyrocore.calib",),
    ("gyrocore.loop",),
    ("gyrocore.calibrator",),
    ("gyrocore.fleet",),
    ("gyrocore.cli",),
)
#: Modules that may import the CLI: the CLI itself and the console-script entry with its commands.
CLI_USERS = ("gyrocore.cli", "experiments.cli", "experiments.commands")


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    out = {}
    for top in PACKAGES:
        for p in sorted((REPO / top).rglob("*.py")):
            out[_module_name(p)] = p
    return out


MODULES = _modules()


def _resolve(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    parts = mod.split(".")
    base = parts if is_pkg else parts[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _known(name: str) -> str | None:
    """The longest project module that ``name`` names (a module, or an attribute of one)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(mod: str) -> dict[str, set[str]]:
    """{imported absolute name: line numbers} of every import statement in ``mod``."""
    path = MODULES[mod]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    out: dict[str, set[str]] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(mod, is_pkg, node)
            # ``from pkg import sub`` imports the submodule; ``from mod import name`` the module
            names = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for n in names:
            out.setdefault(n, set()).add(f"{path.relative_to(REPO)}:{node.lineno}")
    return out


def project_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (package ``__init__`` files counted as modules)."""
    g = {}
    for m in MODULES:
        g[m] = {k for n in imports_of(m) if (k := _known(n)) is not None and k != m}
    return g


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def _unit(mod: str) -> str | None:
    """The layer unit of a gyrocore module (``gyrocore.calib.lsq`` -> ``gyrocore.calib``)."""
    if mod == "gyrocore":
        return None
    parts = mod.split(".")
    return ".".join(parts[:2])


def _layer(unit: str) -> int:
    for i, units in enumerate(LAYERS):
        if unit in units:
            return i
    raise AssertionError(f"{unit} is in no layer of docs/ARCHITECTURE.md (add it to LAYERS and the doc)")


def test_no_import_circles():
    cycles = _cycles(project_graph())
    assert cycles == [], f"import circles: {cycles}"


def test_cycle_finder_finds_a_circle():
    # the finder itself: a -> b -> c -> a is one circle, d hangs off it
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_gyrocore_layers():
    bad = []
    for m in MODULES:
        if not m.startswith("gyrocore.") or m == "gyrocore":
            continue
        mine = _unit(m)
        for name, where in imports_of(m).items():
            tgt = _known(name)
            if tgt is None or not tgt.startswith("gyrocore") or tgt == "gyrocore":
                continue
            unit = _unit(tgt)
            if unit == mine:
                continue
            if _layer(unit) >= _layer(mine):
                bad.append(
                    f"{m} imports {tgt} ({sorted(where)[0]}): layer {_layer(mine)} may not import layer {_layer(unit)}"
                )
    assert not bad, "\n".join(bad)


def test_every_gyrocore_unit_has_a_layer():
    for m in MODULES:
        if m.startswith("gyrocore."):
            _layer(_unit(m))


def test_nothing_below_the_cli_imports_it():
    bad = []
    for m in MODULES:
        if any(m == u or m.startswith(u + ".") for u in CLI_USERS):
            continue
        for name, where in imports_of(m).items():
            tgt = _known(name) or name
            if any(tgt == u or tgt.startswith(u + ".") for u in CLI_USERS):
                bad.append(f"{m} imports {tgt} ({sorted(where)[0]})")
    assert not bad, "\n".join(bad)


def test_gyrocore_never_imports_sim_or_mujoco():
    bad = []
    for m in MODULES:
        if not m.startswith("gyrocore"):
            continue
        for name, where in imports_of(m).items():
            top = name.split(".")[0]
            if top in ("sim", "mujoco", "experiments"):
                bad.append(f"{m} imports {name} ({sorted(where)[0]})")
    assert not bad, "\n".join(bad)


_BLOCKER = r"""
import importlib, importlib.abc, pkgutil, sys

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("sim", "mujoco", "experiments"):
            raise ImportError(f"{name} is blocked: gyrocore must not import it")
        return None

sys.meta_path.insert(0, Block())
import gyrocore
names = [m.name for m in pkgutil.walk_packages(gyrocore.__path__, "gyrocore.")]
for n in names:
    importlib.import_module(n)
assert not [m for m in sys.modules if m.split(".")[0] in ("sim", "mujoco", "experiments")]
print(len(names))
"""


def test_every_gyrocore_module_imports_without_sim_and_mujoco():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-c", _BLOCKER], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(r.stdout.strip()) == sum(1 for m in MODULES if m.startswith("gyrocore."))


@pytest.mark.parametrize("mod", ["gyrocore"])
def test_importing_gyrocore_is_cheap(mod):
    code = (
        f"import sys; import {mod}; "
        "heavy = [m for m in ('matplotlib', 'dask', 'distributed', 'scipy', 'mujoco', 'numba', 'pandas', 'pyarrow') "
        "if m in sys.modules]; print(','.join(heavy))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "", f"import {mod} loads {r.stdout.strip()}"


def test_public_api_resolves():
    import gyrocore

    assert isinstance(gyrocore.__version__, str) and gyrocore.__version__
    for name in gyrocore.__all__:
        assert getattr(gyrocore, name) is not None, name
    from gyrocore.calib.params import CalibrationResult
    from gyrocore.flight.vibration import analyse

    assert gyrocore.CalibrationResult is CalibrationResult and gyrocore.analyse_vibration is analyse
    with pytest.raises(AttributeError):
        gyrocore.no_such_name  # noqa: B018


def test_no_module_level_boolean_flags_in_gyrocore():
    # research switches live in options objects passed in (e.g. gyrocore.noise.options.NoiseOptions),
    # never in module state that callers flip or tests monkeypatch
    bad = []
    for m, path in MODULES.items():
        if not m.startswith("gyrocore"):
            continue
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            targets = (
                node.targets
                if isinstance(node, ast.Assign)
                else [node.target]
                if isinstance(node, ast.AnnAssign)
                else []
            )
            value = getattr(node, "value", None)
            if isinstance(value, ast.Constant) and isinstance(value.value, bool):
                bad += [f"{path.relative_to(REPO)}:{node.lineno} {t.id}" for t in targets if isinstance(t, ast.Name)]
    assert not bad, "module-level boolean flags: " + ", ".join(bad)
