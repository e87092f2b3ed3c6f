"""The house: the import graph (every import, function-local ones included) has no
circle, and the layers only import downwards: ``models`` (the physics) imports neither
``pipeline`` nor ``mitsuba_ext``; ``mitsuba_ext`` (the plugins) does not import
``pipeline``."""

import ast
import re
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


def test_stages_are_leaves():
    """A stage imports no other stage, and nothing but tests imports a stage: what two of
    them share lives in a library module (``models``, ``pipeline``). A stage runs another
    only through ``pipeline.graph.run_stage``, as the CLI does."""
    bad = [(m, n) for m, targets in imports().items() for n in targets
           if n.startswith("pipeline.stages.") and not m.startswith("tests.")]
    assert not bad, f"imports of a stage (move what they share into a library module): {bad}"


# The function-local imports of the project's own modules, each a seam on purpose. Every
# other import is at the top of its module.
LAZY = {
    # the fiber registry loads a model's module when a config names it, so that the stages
    # reading fiber tables (bake, train, ...) do not run (nor depend on) every model's code
    ("models/fiber/__init__.py", "models.fiber.mie"): "fiber registry",
    ("models/fiber/__init__.py", "models.fiber.ray"): "fiber registry",
    ("models/fiber/__init__.py", "models.fiber.table"): "fiber registry",
    # the config's validators read model data (a yarn's row, a .bcc file, a migration's
    # period) only where a config has that key: every stage loads the config
    ("pipeline/config.py", "models.bundle"): "config validators",
    ("pipeline/config.py", "models.spectrum"): "config validators",
    ("pipeline/config.py", "models.cloth.bcc"): "config validators",
    # the checked loaders: a stage that reads only bundle tables runs no fiber code, one that
    # reads fiber tables no bundle-table code (dvc.yaml lists each stage's code)
    ("pipeline/artifacts.py", "models.fiber.base"): "checked loaders",
    ("pipeline/artifacts.py", "models.bundle_table"): "checked loaders",
    # the CLI runs every stage: it loads render-scene's code (Mitsuba scenes, images) for that
    # command alone, so that no stage runs it (dvc.yaml lists each stage's code)
    ("pipeline/cli.py", "pipeline.render_scene"): "render-scene command",
    # a Dask worker imports the baker in cluster.warm_up (its plugin, before its first task),
    # not whenever the module is unpickled on its event loop: @dr.syntax runs ast.parse, which
    # CPython 3.11 cannot run in two threads at once (gh-106905)
    ("pipeline/cluster.py", "pipeline.build"): "Dask worker thread",
    ("pipeline/cluster.py", "models.bake"): "Dask worker thread",
    # mpmath is in the test extra only
    ("pipeline/stages/stability.py", "models.fiber.mie_reference"): "optional mpmath",
}


def local_imports() -> set:
    """``{(file, imported project module)}`` of the imports inside functions."""
    found = set()
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            name = module_name(path)
            package = name if path.name == "__init__.py" else name.rpartition(".")[0]
            for fn in ast.walk(ast.parse(path.read_text())):
                if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                for node in ast.walk(fn):
                    if isinstance(node, ast.ImportFrom):
                        base = node.module or ""
                        if node.level:
                            up = package.split(".")[: len(package.split(".")) - node.level + 1]
                            base = ".".join(up + ([base] if base else []))
                        targets = [f"{base}.{a.name}" if base in PACKAGES or f"{base}.{a.name}" in _modules()
                                   else base for a in node.names]
                    elif isinstance(node, ast.Import):
                        targets = [a.name for a in node.names]
                    else:
                        continue
                    for t in targets:
                        if t.split(".")[0] in PACKAGES:
                            found.add((path.relative_to(ROOT).as_posix(), t))
    return found


def _modules() -> set:
    return {module_name(p) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def test_imports_at_the_top_but_the_listed_seams():
    unlisted = sorted(local_imports() - set(LAZY))
    assert not unlisted, ("function-local imports of the project's modules (move them to the top, or list "
                          f"the seam in LAZY with its reason): {unlisted}")


def test_stages_read_only_artifacts():
    """The product's data path holds no document: no stage reads a file under docs/ (the
    benches' records are for the documents, ``python -m pipeline.figures``)."""
    bad = [p.name for p in (ROOT / "pipeline" / "stages").glob("*.py")
           if re.search(r"""/\s*["']docs["']|["']docs["']\s*/|Path\(\s*["']docs""", p.read_text())]
    assert not bad, f"stages reading docs/: {bad}"


def runs_main(source: str) -> bool:
    """Whether a module's top level has ``if __name__ == "__main__":`` calling ``main``."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test) and "__name__" in ast.unparse(node.test):
            return any(isinstance(n, ast.Call) and ast.unparse(n.func) == "main" for n in ast.walk(node))
    return False


def test_every_bench_imports_and_has_a_main():
    """A bench whose imports broke when code moved fails here, not on the day someone runs it;
    and ``python -m pipeline.bench.NAME`` runs its ``main`` (a module that only defines it
    exits silently, having measured nothing). The check of the guard can fail: a module
    without one, or whose guard calls something else, is told apart."""
    import importlib

    names = [p.stem for p in (ROOT / "pipeline" / "bench").glob("*.py") if p.stem not in ("__init__", "results")]
    assert "encoding" in names
    for name in names:
        module = importlib.import_module(f"pipeline.bench.{name}")
        assert callable(getattr(module, "main", None)), f"pipeline.bench.{name} has no main()"
        assert runs_main((ROOT / "pipeline" / "bench" / f"{name}.py").read_text()), \
            f"python -m pipeline.bench.{name} does not call main(): end it with `if __name__ == \"__main__\":`"
    assert not runs_main("def main():\n    pass\n")
    assert not runs_main('def main():\n    pass\n\n\nif __name__ == "__main__":\n    print()\n')
    assert runs_main('def main():\n    pass\n\n\nif __name__ == "__main__":\n    raise SystemExit(main())\n')
