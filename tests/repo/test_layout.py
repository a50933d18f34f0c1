"""The package's layout holds: no import cycle among s3k's modules (function-level imports count), no module
over 500 lines, and no test importing the benchmark scripts (their logic lives in the library)."""

from __future__ import annotations

import ast
from pathlib import Path

from helpers.paths import REPO as ROOT

PACKAGE = ROOT / "s3k"
MAX_LINES = 500


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The s3k modules ``name`` imports anywhere in its source (top level, functions, TYPE_CHECKING)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            targets = [base, *(f"{base}.{a.name}" for a in node.names)]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):  # a package's own children
                found.add(target)
    return found


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def test_no_import_cycle_in_s3k():
    modules = _modules()
    graph = {name: _imported(name, path, modules) for name, path in modules.items()}
    assert "s3k.data.dataset" in graph and "s3k.data.checks" in graph["s3k.data"]
    cycles = _cycles(graph)
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_cycle_check_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_over_500_lines():
    too_long = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(ROOT).as_posix()
        lines = len(path.read_text().splitlines())
        if lines > MAX_LINES:
            too_long[rel] = lines
    assert not too_long, f"modules over {MAX_LINES} lines: {too_long}"


def test_tests_do_not_import_benchmarks():
    importers = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            if any(n == "benchmarks" or n.startswith("benchmarks.") for n in names):
                importers.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not importers, f"tests importing benchmarks/: {importers}"


ROOMS_OF_SHORT_FUNCTIONS = ("detector", "readout", "train", "inference", "data", "label")
MAX_FUNCTION_LINES = 80


def test_no_function_of_the_detector_readout_training_inference_data_and_label_rooms_is_over_80_lines():
    long = []
    for room in ROOMS_OF_SHORT_FUNCTIONS:
        for path in sorted((PACKAGE / room).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                    if lines > MAX_FUNCTION_LINES:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert long == []


LAYERS = [  # highest first: a room imports from its own layer and the layers below, never above
    ["cli"],
    ["label", "sim", "robot", "experiments"],
    ["inference", "train"],
    ["detector"],
    ["readout", "model", "networks"],
    ["data", "geometry", "base", "rigcal", "config", "config_fields", "config_files", "budget", "run_folder"],
]


def test_imports_go_downwards_only():
    """cli -> apps and experiments -> inference and training -> detector -> read-out, model, losses ->
    data, geometry, heatmaps: no module imports a room of a higher layer (docs/architecture.md)."""
    rank = {room: i for i, rooms in enumerate(LAYERS) for room in rooms}
    upwards, unplaced = [], set()
    for path in sorted(PACKAGE.rglob("*.py")):
        room = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        if room == "__init__":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level
                     else [])
            for name in names:
                if not name.startswith("s3k."):
                    continue
                target = name.split(".")[1]
                if target not in rank or room not in rank:
                    unplaced.add(target if target not in rank else room)
                elif rank[target] < rank[room]:
                    upwards.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not unplaced, f"rooms missing from LAYERS: {sorted(unplaced)}"
    assert upwards == []


HEAVY_OPTIONAL = {  # imported where used, so that a command that does not need one never pays for it
    "onnx", "onnxruntime", "google.protobuf",  # the export extra (protobuf comes with onnx)
    "sleap_io", "pynwb", "ndx_pose",  # the formats extra
    "gymnasium", "stable_baselines3",  # the robot extra
    "fastapi", "uvicorn",  # the label extra
    "rerun",  # the stream extra
    "mujoco",  # the simulator: an OpenGL context on import
    "matplotlib", "tensorboard", "torch.utils.tensorboard",  # seconds to import, for figures and logs only
    "ray",  # the cluster extra: s3k track --manifest, sweeps on a cluster
}


def _import_targets(node: ast.Import | ast.ImportFrom, name: str, path: Path) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    base = node.module or ""
    if node.level:
        up = package.split(".")[: len(package.split(".")) - node.level + 1]
        base = ".".join([*up, base] if base else up)
    return [base, *(f"{base}.{a.name}" for a in node.names)]


def _heavy_modules(modules: dict[str, Path]) -> set[str]:
    """The s3k modules that import a heavy optional dependency, or such a module, at their top level."""
    top: dict[str, list[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        nodes = [n for stmt in tree.body if not isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                                   ast.ClassDef)) for n in ast.walk(stmt)]
        top[name] = [t for n in nodes if isinstance(n, (ast.Import, ast.ImportFrom))
                     for t in _import_targets(n, name, path)]
    heavy = {name for name, targets in top.items() if any(_is_heavy(t) for t in targets)}
    while True:
        more = {name for name, targets in top.items()
                if name not in heavy and any(t in heavy for t in targets)}
        if not more:
            return heavy
        heavy |= more


def _is_heavy(target: str) -> bool:
    return any(target == h or target.startswith(h + ".") for h in HEAVY_OPTIONAL)


def test_imports_inside_functions_are_only_of_heavy_optional_dependencies():
    """Every other import is at the top of its module, where a reader sees what the module needs. Inside a
    function are only imports of HEAVY_OPTIONAL and of the s3k modules that import one, and fallbacks inside
    ``try`` (``tomllib`` before Python 3.11)."""
    modules = _modules()
    heavy = _heavy_modules(modules)
    inside = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        guarded = {id(n) for t in ast.walk(tree) if isinstance(t, ast.Try) for n in ast.walk(t)}
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in guarded:
                    continue
                targets = _import_targets(node, name, path)
                if not any(_is_heavy(t) or t in heavy for t in targets):
                    inside.append(f"{path.relative_to(ROOT)}:{node.lineno} {targets[0]}")
    assert sorted(set(inside)) == []


def test_the_function_import_rule_sees_an_import_it_must_refuse():
    tree = ast.parse("def f():\n    import json\n    from s3k import errors\n")
    found = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert [_import_targets(n, "s3k.x", PACKAGE / "x.py")[0] for n in found] == ["json", "s3k"]
    assert not _is_heavy("json") and _is_heavy("torch.utils.tensorboard") and not _is_heavy("torch")


LOGGERS_CONFIGURED = {"s3k/cli/__init__.py", "s3k/train/run_setup.py"}  # they set up where records go


def test_the_library_logs_and_never_prints():
    """Outside s3k/cli/ no module calls or passes ``print`` (the library logs to
    ``logging.getLogger(__name__)``; the command line shows the records, s3k.base.messages), and a logger is
    named by its module everywhere but where logging is configured."""
    printing, named = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Name) and node.id == "print" and not rel.startswith("s3k/cli/"):
                printing.append(f"{rel}:{node.lineno}")
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "getLogger" and rel not in LOGGERS_CONFIGURED
                    and not (len(node.args) == 1 and isinstance(node.args[0], ast.Name)
                             and node.args[0].id == "__name__")):
                named.append(f"{rel}:{node.lineno}")
    assert printing == [] and named == []


def test_no_private_name_is_imported_from_another_module():
    """A name that starts with ``_`` is its module's own: another module that needs it gets a public name."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                found += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}" for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
    assert found == []


def test_the_data_room_never_decides_by_a_command_line_flag():
    """Below s3k/cli/ the import's formats are dataclasses (s3k.data.import_labels): no module of the data
    room compares a value with a flag such as ``"--sleap"`` or holds a list of them (its messages may still
    name the option that fixes a problem)."""
    found = []
    for path in sorted((PACKAGE / "data").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            flags = [c for c in ast.walk(node) if isinstance(c, ast.Constant) and isinstance(c.value, str)
                     and c.value.startswith("--")]
            listed = (isinstance(node, (ast.Tuple, ast.List, ast.Set)) and len(node.elts) > 1
                      and len(flags) == len(node.elts))
            if flags and (isinstance(node, ast.Compare) or listed):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert found == []


def test_training_does_not_import_inference():
    """Training reads frames through the detector room (``s3k.detector.detect_store``, ``evaluate_store``);
    ``inference/`` is what is done with a trained detector, beside training, not below it."""
    modules = _modules()
    found = [f"{name} imports {target}" for name, path in modules.items() if name.startswith("s3k.train")
             for target in _imported(name, path, modules) if target.startswith("s3k.inference")]
    assert found == []
