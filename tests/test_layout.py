"""The package's layout holds: no import cycle among s3k's modules (function-level imports count), no module
over 500 lines, and no test importing the benchmark scripts (their logic lives in the library)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
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


ROOMS_OF_SHORT_FUNCTIONS = ("detector", "readout", "train", "inference")
MAX_FUNCTION_LINES = 80


def test_no_function_of_the_detector_readout_training_and_inference_rooms_is_over_80_lines():
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
    ["readout", "model", "losses", "augment", "presets"],
    ["data", "geometry", "heatmaps", "errors", "fileio", "outputs", "ranges", "draw", "calibration",
     "recalibration", "config", "config_files", "run_folder", "metrics"],
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


def test_training_does_not_import_inference():
    """Training reads frames through the detector room (``s3k.detector.detect_store``, ``evaluate_store``);
    ``inference/`` is what is done with a trained detector, beside training, not below it."""
    modules = _modules()
    found = [f"{name} imports {target}" for name, path in modules.items() if name.startswith("s3k.train")
             for target in _imported(name, path, modules) if target.startswith("s3k.inference")]
    assert found == []
