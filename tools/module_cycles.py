#!/usr/bin/env python3
"""Whether a crate's top-level modules import each other in a cycle.

    python3 tools/module_cycles.py [SRC_DIR ...]   (default: src tools/vkdr bindings/python/src)

A module is a file or folder directly under SRC_DIR; it depends on another where any of its
files' code (comments left out) names `crate::other` (in a `use` or a path). A module's own children (`super::`) do
not count. Prints each directory's edges' count and any cycle; exits 1 on a cycle.
"""
import re
import sys
from pathlib import Path


def modules(root: Path) -> dict[str, list[Path]]:
    found: dict[str, list[Path]] = {}
    for path in root.rglob("*.rs"):
        rel = path.relative_to(root)
        if rel.parts[0] in ("tests", "benches", "target"):
            continue
        name = rel.parts[0].removesuffix(".rs")
        if name in ("lib", "main"):
            continue
        found.setdefault(name, []).append(path)
    return found


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for next_node in sorted(graph.get(node, ())):
            if state.get(next_node) == 1:
                return stack[stack.index(next_node):] + [next_node]
            if next_node not in state and (found := visit(next_node)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def main() -> int:
    roots = [Path(p) for p in sys.argv[1:]] or [
        Path("src"), Path("tools/vkdr"), Path("bindings/python/src")]
    failed = False
    for root in roots:
        mods = modules(root)
        graph: dict[str, set[str]] = {}
        for name, files in mods.items():
            # Code only: doc links and comments name modules without importing them.
            text = "\n".join(re.sub(r"//.*", "", f.read_text()) for f in files)
            # `use crate::{a, b::c}` and `crate::a::...` paths.
            names = set(re.findall(r"\bcrate::(\w+)", text))
            for group in re.findall(r"\bcrate::\{([^}]*)\}", text):
                names |= set(re.findall(r"(?:^|,)\s*(\w+)", group))
            graph[name] = {n for n in names if n in mods and n != name}
        edges = sum(len(v) for v in graph.values())
        found = cycle(graph)
        print(f"{root}: {len(mods)} modules, {edges} imports between them, "
              + ("cycle: " + " -> ".join(found) if found else "no cycle"))
        failed |= found is not None
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
