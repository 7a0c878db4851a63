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
    ("stewart_calib", "resources", "progress"),
    ("samples", "config", "chi_square"),
    ("model",),
    ("estimate", "instruments"),
    ("io",),
    ("factors", "analysis", "simulation", "viz"),
    ("estimators", "links"),
    ("workflows",),
    ("reproduction", "sweep"),
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
    tree = ast.parse(path.read_text(encoding="utf-8"))
    # an import under `if TYPE_CHECKING:` names an annotation's type: no arrow at run time
    typing_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and ast.unparse(node.test) in {"TYPE_CHECKING", "typing.TYPE_CHECKING"}
        for statement in node.body
        for inner in ast.walk(statement)
    }
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
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
    # importing the platform, and a relative 'from ..model import kinematics' must name that module.
    graph = _graph()
    assert "stewart_calib.model.platform" in graph["stewart_calib.estimators.ekf"]
    assert "stewart_calib.model.kinematics" in graph["stewart_calib.estimators.measurement"]


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
LEG_SET_MODEL = {
    "model/platform.py",
    "model/kinematics.py",
    "model/_kernels.py",
    "model/statics.py",
    "model/drive.py",
    "model/rotary.py",
    "io/platform_file.py",  # the platform file's tables hold one row a leg (spec §2, §15)
}


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


#: the fields of the prismatic leg set, which only the leg models (and the files at the edge) name
LEG_GEOMETRY_FIELDS = {"base_joints", "platform_joints", "initial_lengths"}
#: the modules (paths in the package; a path ending in "/" holds all below it) that may name them:
#: the leg-set model and its files, and each other one with its reason
LEG_FIELD_MODULES = {
    "model/",
    "io/",  # the files at the edge: the platform file, the controllers' formats
    "analysis/identifiability.py",  # the compiled whitened rows' arguments (prismatic legs only)
    "sweep/spec.py",  # the ring-platform family builds prismatic legs
}


def test_only_the_leg_models_name_the_leg_fields():
    """Analyses and workflows reach the legs through DriveModel and the leg model's protocol
    (parameter vector, names, residual, Jacobians, FK, IK): a rotary drive has no base joints."""
    named = set()
    for path in PACKAGE.rglob("*.py"):
        where = str(path.relative_to(PACKAGE))
        if any(
            where == allowed or (allowed.endswith("/") and where.startswith(allowed)) for allowed in LEG_FIELD_MODULES
        ):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            attribute = isinstance(node, ast.Attribute) and node.attr in LEG_GEOMETRY_FIELDS
            if attribute or (isinstance(node, ast.Constant) and node.value in LEG_GEOMETRY_FIELDS):
                named.add(where)
    assert named == set(), sorted(named)


def test_the_leg_field_check_sees_fields():
    # the check above passes vacuously if it reads nothing: the leg-set model itself names them
    tree = ast.parse((PACKAGE / "model" / "kinematics.py").read_text(encoding="utf-8"))
    assert any(isinstance(node, ast.Attribute) and node.attr in LEG_GEOMETRY_FIELDS for node in ast.walk(tree))
