"""The package's layout: no import cycle among pmjax's modules (module-level or inside functions)."""

import ast
from pathlib import Path

import pmjax

ROOT = Path(pmjax.__file__).parent


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set) -> set:
    """The pmjax modules ``path`` imports anywhere (a ``from X import y``
    counts as X.y where that is a module)."""
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("pmjax")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("pmjax"):
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                out.add(sub if sub in modules else target)
    return {m for m in out if m in modules and m != here}


def test_no_import_cycles():
    paths = [p for p in ROOT.rglob("*.py")]
    # Compiled extensions are modules too (they import nothing of pmjax).
    extensions = {module_name(p.with_name(p.name.split(".")[0] + ".py")) for p in ROOT.rglob("*.so")}
    modules = {module_name(p) for p in paths} | extensions
    graph = {module_name(p): imports_of(p, modules) for p in paths}
    graph.update({m: set() for m in extensions})
    # The package itself re-exports its modules: only edges out of the
    # package's modules count (an edge into a package's __init__ from inside it
    # would be a cycle through the re-exports).
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles
