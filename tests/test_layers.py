"""The import graph of stewart_calib: no circle, and every arrow points down the layers.

Imports are read from the source with ``ast`` (also those inside functions: a lazy import is
still an arrow). A module of a new top-level name must be given a layer here, which is the
moment to decide where it belongs (docs/architecture.md draws the same layers).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "stewart_calib"

#: bottom first; a module may import from its own group and from groups of lower layers only.
LAYERS = (
    ("_jit", "errors"),
    ("inputs", "memory"),
    ("stewart_calib", "_kernels", "resources", "progress"),
    ("samples", "config", "rotations", "chi_square"),
    ("platform",),
    ("kinematics", "unknowns"),
    ("statics",),
    ("model",),
    ("drive",),
    ("estimate", "instruments"),
    ("factors", "io", "identifiability", "accuracy", "compensation", "plausibility", "simulation", "viz"),
    ("planning", "estimators", "diagnosis", "links"),
    ("online", "reproduction", "sweep"),
    ("calibration", "validation"),
    ("pipelines",),
    ("cli",),
    ("__main__",),
)
RANK = {group: rank for rank, groups in enumerate(LAYERS) for group in groups}


def _module_name(path: Path) -> str:
    parts = ("stewart_calib", *path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in PACKAGE.rglob("*.py")}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The stewart_calib modules ``name`` imports (a ``from package import module`` names the module)."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        found.update(target for target in targets if target in known)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) - {name} for name, path in modules.items()}


def _group(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def test_every_module_has_a_layer():
    assert sorted({_group(m) for m in _graph()} - set(RANK)) == []


def test_imports_point_down_the_layers():
    upward = [
        f"{module} -> {target}"
        for module, targets in _graph().items()
        for target in targets
        if _group(target) != _group(module) and RANK[_group(target)] >= RANK[_group(module)]
    ]
    assert upward == []


def test_import_graph_has_no_circle():
    graph, state, circles = _graph(), {}, []

    def visit(module: str, path: list[str]) -> None:
        state[module] = "open"
        for target in sorted(graph[module]):
            if state.get(target) == "open":
                circles.append(" -> ".join(path[path.index(target) :] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert circles == []


def test_the_checker_sees_arrows():
    # The checks above pass vacuously if imports are not found: the estimators must be seen
    # importing the platform, and a relative 'from .. import kinematics' must name that module.
    graph = _graph()
    assert "stewart_calib.platform" in graph["stewart_calib.estimators.ekf"]
    assert "stewart_calib.kinematics" in graph["stewart_calib.estimators.graph"]


def test_pipelines_import_nothing_private_from_each_other():
    # A command's private helper is its own: one another command needs belongs below pipelines/
    # (or is made public in its module), so that no command is the hidden library of another.
    modules = _modules()
    borrowed = []
    for name, path in modules.items():
        if not name.startswith("stewart_calib.pipelines."):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        siblings = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                source = f"stewart_calib.pipelines.{node.module}" if node.module else "stewart_calib.pipelines"
                for alias in node.names:
                    target = f"{source}.{alias.name}"
                    if target in modules:
                        siblings.add(alias.asname or alias.name)  # a sibling module, its attributes read below
                    elif source != "stewart_calib.pipelines" and alias.name.startswith("_"):
                        borrowed.append(f"{name} imports {source}.{alias.name}")
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in siblings
                and node.attr.startswith("_")
            ):
                borrowed.append(f"{name} uses {node.value.id}.{node.attr}")
    assert borrowed == []


#: the leg-set model (docs/architecture.md): the only modules that know a platform has six legs of
#: seven parameters; everything else takes the sizes from the model or from its arrays
LEG_SET_MODEL = {"platform.py", "kinematics.py", "_kernels.py", "statics.py", "drive.py", "model/rotary.py"}


def test_only_the_leg_set_model_names_the_number_of_legs():
    """A 6-RSS hexapod must be a new leg-set model, not a fork of every module that hard-codes six legs."""
    named = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            sized = isinstance(node, ast.Name) and node.id in {"N_LEGS", "N_PARAMS", "N_PARAMS_PER_LEG"}
            six_loop = (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "range"
                and [ast.unparse(arg) for arg in node.args] == ["6"]
            )
            if sized or six_loop:
                named.add(str(path.relative_to(PACKAGE)))
    assert named <= LEG_SET_MODEL, sorted(named - LEG_SET_MODEL)
