"""The package's import graph: imports flow one way through the stages, without cycles
and without reaching into another stage's private parts (README "Architecture").

The graph is read from the source (every `import` statement, also those inside
functions), so a hidden cycle through a function-level import counts too."""

import ast
import inspect
import itertools
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "evhsi_jax"

# Stages in data-flow order: a module may import its own stage or an earlier one.
STAGES = [
    ("base", {"_base"}),
    ("model", {"_model"}),
    ("simulate", {"_simulate"}),
    ("io", {"_io"}),
    ("reconstruct", {"_reconstruct"}),
    ("products", {"_calibrate", "_design", "_baselines", "_video"}),
    (
        "interface",
        {"cli", "__main__", "__init__", "_demo", *("forward io reconstruction "
         "calibration video design baselines sharding metrics").split()},
    ),
]
RANK = {comp: i for i, (_, comps) in enumerate(STAGES) for comp in comps}


def _modules():
    """`{dotted name below evhsi_jax: path}`; a package is named by its folder."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1] or ("__init__",)
        out[".".join(parts)] = path
    return out


def _imports(mods):
    """`[(importer, imported module, imported names)]`, module names as in `_modules`."""
    edges = []
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        pkg = name.split(".") if is_pkg and name != "__init__" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg[: len(pkg) - node.level + 1]
                    target = base + (node.module.split(".") if node.module else [])
                elif node.module and node.module.split(".")[0] == "evhsi_jax":
                    target = node.module.split(".")[1:]
                else:
                    continue
                for alias in node.names:
                    sub = ".".join(target + [alias.name])
                    if sub in mods:  # `from . import _shard`: the module itself
                        edges.append((name, sub, ()))
                    else:
                        edges.append((name, ".".join(target) or "__init__", (alias.name,)))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == "evhsi_jax":
                        edges.append((name, ".".join(alias.name.split(".")[1:]), ()))
    return edges


def _component(module: str) -> str:
    return module.split(".")[0]


@pytest.fixture(scope="module")
def graph():
    mods = _modules()
    return mods, _imports(mods)


def test_every_module_has_a_stage(graph):
    mods, _ = graph
    missing = sorted({_component(m) for m in mods} - set(RANK))
    assert not missing, f"modules without a stage in tests/test_architecture.py: {missing}"


def test_imports_flow_one_way(graph):
    _, edges = graph
    upward = [
        f"{a} -> {b}"
        for a, b, _ in edges
        if _component(a) != _component(b) and RANK[_component(b)] > RANK[_component(a)]
    ]
    assert not upward, "imports against the data flow:\n" + "\n".join(upward)


def test_no_private_reach_across_components(graph):
    """Across components only a package's front (`_reconstruct`, not
    `_reconstruct._pixels`) and only public names (no leading underscore)."""
    _, edges = graph
    bad = []
    for a, b, names in edges:
        if _component(a) == _component(b) or _component(a) == "__init__":
            continue
        if "." in b:
            bad.append(f"{a} -> {b} (inside another package)")
        bad += [f"{a} -> {b}.{n} (private name)" for n in names if n.startswith("_")]
    assert not bad, "\n".join(bad)


def test_no_import_cycle_between_components(graph):
    _, edges = graph
    deps = {}
    for a, b, _ in edges:
        ca, cb = _component(a), _component(b)
        if ca != cb:
            deps.setdefault(ca, set()).add(cb)

    def reaches(src, dst, seen=()):
        return any(
            n == dst or (n not in seen and reaches(n, dst, (*seen, n)))
            for n in deps.get(src, ())
        )

    cycles = [
        f"{a} <-> {b}"
        for a, b in itertools.combinations(sorted(deps), 2)
        if reaches(a, b) and reaches(b, a)
    ]
    assert not cycles, "import cycles: " + ", ".join(cycles)


def test_the_checker_sees_a_violation(tmp_path, monkeypatch):
    """The checks above can fail: a planted upward and private import is found."""
    pkg = tmp_path / "evhsi_jax"
    for stage in ("_model", "_reconstruct"):
        (pkg / stage).mkdir(parents=True)
        (pkg / stage / "__init__.py").write_text("")
    (pkg / "_model" / "_rig.py").write_text("from .._reconstruct._pixels import _secret\n")
    (pkg / "_reconstruct" / "_pixels.py").write_text("from .._model import Rig\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", pkg)
    mods = _modules()
    edges = _imports(mods)
    assert ("_model._rig", "_reconstruct._pixels", ("_secret",)) in edges
    assert ("_reconstruct._pixels", "_model", ("Rig",)) in edges
    with pytest.raises(AssertionError, match="against the data flow"):
        test_imports_flow_one_way((mods, edges))
    with pytest.raises(AssertionError, match="private name"):
        test_no_private_reach_across_components((mods, edges))
    with pytest.raises(AssertionError, match="import cycles"):
        test_no_import_cycle_between_components((mods, edges))


TOP_LEVEL = {
    "Rig", "Scene", "EventStream", "Calibration", "load_scene", "read_events",
    "write_events", "load_cube", "save_cube", "load_calibration", "save_calibration",
    "simulate", "calibrate", "reconstruct", "reconstruct_sweeps", "evaluate",
    "write_png", "cube_to_srgb", "enable_compilation_cache",
    "forward", "io", "reconstruction", "calibration", "video", "design", "baselines",
    "sharding", "metrics",
}  # fmt: skip


def test_public_surface():
    """The top level is the verbs and the objects they pass; the rest is in the
    namespaces, whose every name resolves. A name added or dropped fails here, so a
    change of the public API is a decision (update this set and the README)."""
    import evhsi_jax as ev

    assert set(ev.__all__) == TOP_LEVEL
    # (sub-modules a tool imported, e.g. jaxtyping's pytest hook, are not API)
    public = {
        n
        for n in dir(ev)
        if not n.startswith("_")
        and (not inspect.ismodule(getattr(ev, n)) or n in ev._NAMESPACES)
    }
    assert public == TOP_LEVEL
    for ns in ev._NAMESPACES:
        mod = getattr(ev, ns)
        assert mod.__all__, ns
        for name in mod.__all__:
            assert getattr(mod, name) is not None, f"{ns}.{name}"
        assert {n for n in dir(mod) if not n.startswith("_")} >= set(mod.__all__)
    # A name that moved off the top level says where it went.
    with pytest.raises(AttributeError, match=r"evhsi_jax\.calibration\.chart_data"):
        ev.chart_data  # noqa: B018
