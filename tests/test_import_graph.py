"""The import graph of src/volren has no cycle (issue 42 item 3): every import counts, at the top or inside a function
(a lazy import still ties the two modules), except those under ``if TYPE_CHECKING:``, which never run. Parsed, not
imported: fast, and it sees the imports of code paths no test takes."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"


def modules() -> dict[str, Path]:
    out = {}
    for path in (SRC / "volren").rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def runtime_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """The import statements of ``tree`` that run, at any depth: all but those in an ``if TYPE_CHECKING:`` body."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def import_graph() -> dict[str, set[str]]:
    """Module -> the volren modules it imports (``from a.b import c`` imports a.b, or a.b.c where that is a module)."""
    mods = modules()

    def known(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in runtime_imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            graph[name] |= {t for t in map(known, targets) if t is not None and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
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
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_finder_sees_a_lazy_cycle_and_skips_type_checking():
    """The checker itself: a cycle closed by an import inside a function is one; an import under TYPE_CHECKING is
    not."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    lazy = ast.parse("def f():\n    import x\nif TYPE_CHECKING:\n    import y\nelse:\n    import z\n")
    assert sorted(n.names[0].name for n in runtime_imports(lazy)) == ["x", "z"]


def test_src_volren_has_no_import_cycle():
    graph = import_graph()
    assert len(graph) >= 100 and "volren.data.grid" in graph["volren.data.loaders"]  # the graph is read
    assert "volren.render.frame" not in graph["volren.output"]  # named under TYPE_CHECKING only
    found = cycles(graph)
    assert not found, "import cycles (each a set of modules that import each other): " + "; ".join(
        " <-> ".join(c) for c in found)


FRONT_ENDS = ("volren", "volren._api", "volren._entry", "volren.cli", "volren.serve", "volren.distributed",
              "volren.bench", "volren.notebook")
"""the front ends (the package's own names are the API's): they build on the plan and everything below it"""


def layer(module: str) -> int:
    """0: data, scenes, renderers and their helpers; 1: the plan; 2: a front end."""
    if any(module == f or (f != "volren" and module.startswith(f + ".")) for f in FRONT_ENDS):
        return 2
    return 1 if module == "volren.plan" or module.startswith("volren.plan.") else 0


def test_arrows_go_one_way_data_scene_render_plan_front_ends():
    """Nothing below the plan imports the plan or a front end, and the plan imports no front end (issue 42 item 3:
    the plan had imported the API for a loaded file's defaults)."""
    graph = import_graph()
    assert layer("volren.plan.spec") == 1 and layer("volren.serve.loop") == 2 and layer("volren.render") == 0
    up = sorted(f"{a} -> {b}" for a, targets in graph.items() for b in targets if layer(b) > layer(a))
    assert not up, "imports against the layers (data -> scene -> render -> plan -> front ends): " + "; ".join(up)
