"""The house: the import graph (every import, function-local ones included) has no
circle, and the layers only import downwards: ``models`` (the physics) imports neither
``pipeline`` nor ``mitsuba_ext``; ``mitsuba_ext`` (the plugins) does not import
``pipeline``."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "mitsuba_ext", "pipeline")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports() -> dict:
    """``{module: {imported project modules}}`` from the source (ast), all imports."""
    modules = {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" for a in node.names] + [base]
            else:
                continue
            for t in targets:
                while t and t not in modules:  # 'from x import function' names the module x
                    t = t.rpartition(".")[0]
                if t and t != name and not name.startswith(t + ".") and t not in PACKAGES:
                    found.add(t)
        graph[name] = found
    return graph


def test_no_import_circles():
    graph = imports()
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == "open":
                cycles.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "import circles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_layers_import_downwards():
    bad = [(m, n) for m, targets in imports().items() for n in targets
           if (m.startswith("models") and n.split(".")[0] in ("pipeline", "mitsuba_ext"))
           or (m.startswith("mitsuba_ext") and n.startswith("pipeline"))]
    assert not bad, f"upward imports: {bad}"
