"""The package's import graph has no cycles: every `import` / `from` in uavsearch/**.py, function bodies
included, resolved to the uavsearch module it names."""

from __future__ import annotations

import ast
from pathlib import Path

import uavsearch

PKG_DIR = Path(uavsearch.__file__).resolve().parent


def _modules() -> dict[str, Path]:
    out = {}
    for path in PKG_DIR.rglob("*.py"):
        parts = list(path.relative_to(PKG_DIR.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest uavsearch module that `name` (a dotted module or module.attribute) lies in."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    stem = ".".join(base + ([node.module] if node.module else []))
                else:
                    stem = node.module or ""
                # `from a import b`: b may be a submodule (edge to a.b) or a name in a (edge to a)
                targets = [f"{stem}.{a.name}" for a in node.names]
            for t in targets:
                dep = _resolve(t, modules) if t.split(".")[0] == "uavsearch" else None
                if dep and dep != mod:
                    graph[mod].add(dep)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as [m0, m1, ..., m0], or None (iterative DFS with colours)."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = {m: WHITE for m in graph}
    for root in sorted(graph):
        if colour[root] != WHITE:
            continue
        stack = [(root, iter(sorted(graph[root])))]
        path = [root]
        colour[root] = GREY
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                colour[node] = BLACK
                stack.pop()
                path.pop()
            elif colour[nxt] == GREY:
                return path[path.index(nxt):] + [nxt]
            elif colour[nxt] == WHITE:
                colour[nxt] = GREY
                stack.append((nxt, iter(sorted(graph[nxt]))))
                path.append(nxt)
    return None


def test_graph_sees_function_level_imports():
    g = import_graph()
    assert "uavsearch.errors" in g["uavsearch.cli"]
    assert len(g) > 40


def test_find_cycle_reports_the_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_package_import_graph_is_acyclic():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


# Folders whose sub-folders are rooms of their own (search/data, search/train, search/evaluate).
SPLIT_ROOMS = ("uavsearch.search",)


def _room(module: str) -> str:
    """A module's room: uavsearch.search.x -> uavsearch.search; uavsearch.search.train.x -> uavsearch.search.train;
    uavsearch.flight.mavlink.x -> uavsearch.flight; uavsearch.cli -> uavsearch.cli."""
    parts = module.split(".")
    room = ".".join(parts[:2])
    if room in SPLIT_ROOMS and len(parts) > 2 and (PKG_DIR.joinpath(*parts[1:3])).is_dir():
        return ".".join(parts[:3])
    return room


def re_entries(graph: dict[str, set[str]]) -> list[tuple[str, str, str]]:
    """(a, b, c): a imports b in another room, and b's imports lead back to c in a's room
    (a back-and-forth between rooms such as search -> logs -> search)."""
    out = []
    for a in sorted(graph):
        for b in sorted(graph[a]):
            if _room(b) == _room(a):
                continue
            seen, stack = {b}, [b]
            while stack:
                for x in graph[stack.pop()]:
                    if x not in seen:
                        seen.add(x)
                        stack.append(x)
            back = sorted(x for x in seen if _room(x) == _room(a))
            if back:
                out.append((a, b, back[0]))
    return out


def test_re_entries_are_found():
    g = {"p.s.a": {"p.l.b"}, "p.l.b": {"p.s.c"}, "p.s.c": set()}
    assert re_entries(g) == [("p.s.a", "p.l.b", "p.s.c")]


def test_no_import_leaves_a_room_and_comes_back():
    bad = re_entries(import_graph())
    assert not bad, "imports that leave a room and lead back into it: " + "; ".join(
        f"{a} -> {b} -> ... -> {c}" for a, b, c in bad)


def reaches(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module that `start`'s imports lead to."""
    seen, stack = set(), [start]
    while stack:
        for x in graph[stack.pop()]:
            if x not in seen:
                seen.add(x)
                stack.append(x)
    return seen


def test_rooms_of_sub_folders():
    assert _room("uavsearch.search.train.policy") == "uavsearch.search.train"
    assert _room("uavsearch.search.policy") == "uavsearch.search"
    assert _room("uavsearch.search.data") == "uavsearch.search.data"
    assert _room("uavsearch.flight.mavlink.links") == "uavsearch.flight"


# What each room must never reach, directly or through others: the rooms that stand above it. Training and
# evaluation both build on the loop and never on each other; the loop knows nothing of its data, trainers,
# evaluations, of flying or of logs; the recorder knows nothing of what it records.
NEVER_REACHES = {
    "uavsearch.search": ("uavsearch.search.data", "uavsearch.search.train", "uavsearch.search.evaluate",
                         "uavsearch.fly", "uavsearch.logs", "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.search.data": ("uavsearch.search.train", "uavsearch.search.evaluate", "uavsearch.fly",
                              "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.search.train": ("uavsearch.search.evaluate", "uavsearch.fly", "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.search.evaluate": ("uavsearch.search.train", "uavsearch.fly", "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.flight": ("uavsearch.search", "uavsearch.fly", "uavsearch.logs", "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.world": ("uavsearch.flight", "uavsearch.search", "uavsearch.fly", "uavsearch.logs",
                        "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.logs": ("uavsearch.search", "uavsearch.fly", "uavsearch.replay", "uavsearch.cli"),
    "uavsearch.fly": ("uavsearch.replay", "uavsearch.cli"),
    "uavsearch.replay": ("uavsearch.cli",),
    "uavsearch.research": ("uavsearch.cli",),
}


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for mod in sorted(graph):
        banned = NEVER_REACHES.get(_room(mod), ())
        for dep in sorted(reaches(graph, mod)):
            if _room(dep) in banned:
                bad.append(f"{mod} -> ... -> {dep}")
                break
    return bad


def test_upward_imports_are_found():
    g = {"uavsearch.search.train.a": {"uavsearch.search.b"}, "uavsearch.search.b": {"uavsearch.search.evaluate.c"},
         "uavsearch.search.evaluate.c": set()}
    assert upward_imports(g) == ["uavsearch.search.b -> ... -> uavsearch.search.evaluate.c",
                                 "uavsearch.search.train.a -> ... -> uavsearch.search.evaluate.c"]


def test_no_room_imports_a_room_above_it():
    bad = upward_imports(import_graph())
    assert not bad, "imports of a room that stands above: " + "; ".join(bad)


def research_importers(graph: dict[str, set[str]]) -> list[str]:
    """Modules outside the research room (and the command) that import it: its probes build on every room, and
    no room builds on them, so a probe can change without touching the product."""
    return sorted(f"{m} -> {d}" for m in graph for d in graph[m] if _room(d) == "uavsearch.research"
                  and _room(m) not in ("uavsearch.research", "uavsearch.cli"))


def test_research_importers_are_found():
    g = {"uavsearch.search.a": {"uavsearch.research.p"}, "uavsearch.cli": {"uavsearch.research.p"},
         "uavsearch.research.p": {"uavsearch.search.a"}}
    assert research_importers(g) == ["uavsearch.search.a -> uavsearch.research.p"]


def test_only_the_command_imports_the_research_room():
    bad = research_importers(import_graph())
    assert not bad, "the package imports its research room: " + "; ".join(bad)
