#!/usr/bin/env python3
"""The import graph of ptv's sources, from their `use` lines.

    python3 scripts/import_graph.py [FOLDER ...]      # default: src/service
    python3 scripts/import_graph.py src/service --floors app,http,ops,store,model,infra

A file is a node (its module: `src/service/http/mod.rs` is
`crate::service::http`); an arrow A -> B means a `use` in A names an item
of B (`use crate::...`, `use super::...`, `use self::...`, braces
expanded, and paths written inline, `crate::service::jobs::PROCESS_FRAME`;
a path resolves to the longest module that is a file). Only
arrows between files under the FOLDERs count.

It prints the files, the arrows, the cycles (strongly connected
components of more than one file) and the arrows that point back up: the
floors are the longest-path layering of the graph once a feedback arc set
(Eades, Lin and Smyth's greedy heuristic, deterministic) is taken out, and
the arrows of that set are the ones that point up. Each is listed as
`from -> to (names)`, so that a restructuring can be checked by rerunning
this before and after it.

With `--floors A,B,...` (highest first) each file is on the floor of the
first folder below the FOLDER that holds it (a file directly in the
FOLDER is on floor `A` if A is not a folder there, e.g. `app` for
`app.rs` and `mod.rs`); an arrow from a lower floor to a higher one is
listed as `against the floors`. A floor may import its own floor and
those below it.

Re-exports: a module's `pub use` of an item of its own sub-module is
followed to the sub-module that defines it, and is no arrow of the
parent's unless the parent's own code names the item. In an inline module
(`mod tests { ... }`) `super` names the file's own module.
"""

import re
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"


def module_of(path: Path) -> tuple:
    """The module path of a source file, as a tuple (`('service', 'http')`)."""
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] in ("mod", "lib", "main"):
        parts = parts[:-1]
    return tuple(parts)


def strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def inline_depth(text: str):
    """For each offset, how many inline modules (`mod tests { ... }`) it is
    in: there `super` names the file's own module, not its parent."""
    depth = [0] * (len(text) + 1)
    starts = [m.end() - 1 for m in re.finditer(r"\bmod\s+\w+\s*\{", text)]
    for start in starts:
        level, i = 0, start
        while i < len(text):
            if text[i] == "{":
                level += 1
            elif text[i] == "}":
                level -= 1
                if level == 0:
                    break
            i += 1
        for j in range(start, min(i + 1, len(text))):
            depth[j] += 1
    return depth


def use_statements(text: str):
    """The `use` statements (`pub use`, `pub(crate) use` too): their
    bodies, whether they are `pub`, and their inline-module depth."""
    depth = inline_depth(text)
    for match in re.finditer(r"(?:^|[;{}\s])((?:pub(?:\([^)]*\))?\s+)?)use\s+([^;]+);", text):
        body = re.sub(r"\s+as\s+\w+", "", match.group(2))
        yield re.sub(r"\s+", "", body), bool(match.group(1)), depth[match.start(2)]


def expand(tree: str) -> list:
    """`a::{b,c::{d,e}}` -> ['a::b', 'a::c::d', 'a::c::e']."""
    depth, start = 0, None
    for i, ch in enumerate(tree):
        if ch == "{":
            if depth == 0:
                start = i
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth == 0:
                prefix, inner, rest = tree[:start], tree[start + 1 : i], tree[i + 1 :]
                items, level, last = [], 0, 0
                for j, c in enumerate(inner):
                    if c == "{":
                        level += 1
                    elif c == "}":
                        level -= 1
                    elif c == "," and level == 0:
                        items.append(inner[last:j])
                        last = j + 1
                items.append(inner[last:])
                out = []
                for item in items:
                    if item:
                        out.extend(expand(prefix + item + rest))
                return out
    return [tree]


def resolve(path: str, here: tuple, modules: set, inline: int = 0):
    """The file module a `use` path names, or None (std, other crates).
    `inline`: how many inline modules of the file (`mod tests { ... }`)
    the path is written in; each takes one `super` (and `self` there names
    the inline module, which is part of the file)."""
    segments = [s for s in path.split("::") if s]
    if not segments:
        return None
    if segments[0] == "crate":
        base, rest = (), segments[1:]
    elif segments[0] in ("super", "self"):
        base, rest = here, segments
        while rest and rest[0] in ("super", "self"):
            if rest[0] == "super":
                if inline:
                    inline -= 1
                else:
                    base = base[:-1]
            rest = rest[1:]
    elif segments[0] == "ptv":
        base, rest = (), segments[1:]
    else:
        return None
    full = base + tuple(rest)
    for n in range(len(full), -1, -1):
        if full[:n] in modules:
            return full[:n]
    return None


def through_reexports(target: tuple, name: str, reexports: dict) -> tuple:
    """Where `name`, taken from `target`, is defined: a module's `pub use`
    of an item of its own sub-module is followed to that sub-module."""
    seen = set()
    while (target, name) in reexports and (target, name) not in seen:
        seen.add((target, name))
        target = reexports[(target, name)]
    return target


def feedback_arcs(nodes, edges):
    """Eades-Lin-Smyth: an order of the nodes; arrows against it point up."""
    out, into = defaultdict(set), defaultdict(set)
    for a, b in edges:
        out[a].add(b)
        into[b].add(a)
    remaining = set(nodes)
    head, tail = [], []
    while remaining:
        changed = True
        while changed:
            changed = False
            for n in sorted(remaining):
                if not (out[n] & remaining):  # a sink: imports nothing left
                    tail.insert(0, n)
                    remaining.discard(n)
                    changed = True
            for n in sorted(remaining):
                if not (into[n] & remaining):  # a source: nothing left imports it
                    head.append(n)
                    remaining.discard(n)
                    changed = True
        if remaining:
            best = max(
                sorted(remaining),
                key=lambda n: len(out[n] & remaining) - len(into[n] & remaining),
            )
            head.append(best)
            remaining.discard(best)
    order = {n: i for i, n in enumerate(head + tail)}
    # Importers come first in the order (they stand above what they use):
    # an arrow from a later node to an earlier one points back up.
    return {(a, b) for a, b in edges if order[a] > order[b]}


def cycles(nodes, edges):
    """Tarjan's strongly connected components with more than one node."""
    graph = defaultdict(list)
    for a, b in sorted(edges):
        graph[a].append(b)
    index, low, stack, on, found = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(10000)
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return found


def floor_of(path: Path, folder: Path, floors: list):
    """The floor a file stands on (see the module docs)."""
    parts = path.relative_to(folder).parts
    if len(parts) > 1 and parts[0] in floors:
        return parts[0]
    stem = Path(parts[0]).stem
    return stem if stem in floors else floors[0]


def main():
    args = sys.argv[1:]
    floors = []
    if "--floors" in args:
        i = args.index("--floors")
        floors = args[i + 1].split(",")
        args = args[:i] + args[i + 2 :]
    folders = [ROOT / f for f in (args or ["src/service"])]
    files = sorted(p for p in SRC.rglob("*.rs"))
    modules = {module_of(p): p for p in files}
    chosen = {
        module_of(p)
        for p in files
        if any(folder == p or folder in p.parents for folder in folders)
    }
    # A module's `pub use` of an item of its own sub-module (a facade:
    # `pub use self::calibrations::CalibrationRow;` in store/mod.rs) is
    # followed: importing the item through the parent is an arrow to the
    # sub-module that defines it, and the re-export itself is no arrow of
    # the parent's unless the parent's own code names the item.
    known = set(modules)
    texts = {m: strip_comments(modules[m].read_text()) for m in modules}
    statements = {m: list(use_statements(texts[m])) for m in modules}
    reexports = {}
    for module, found in statements.items():
        for body, public, inline in found:
            if not public or inline:
                continue
            for path in expand(body):
                target = resolve(path, module, known)
                name = path.split("::")[-1]
                if target and target[: len(module)] == module and target != module and name != "*":
                    reexports[(module, name)] = target
    edges, names = set(), defaultdict(set)
    for module in sorted(chosen):
        text = texts[module]
        code = re.sub(r"(?:pub(?:\([^)]*\))?\s+)?use\s+[^;]+;", "", text)
        depth = inline_depth(text)
        paths = []
        for body, public, inline in statements[module]:
            for path in expand(body):
                name = path.split("::")[-1]
                if (
                    public
                    and (module, name) in reexports
                    and not re.search(r"\b%s\b" % re.escape(name), code)
                ):
                    continue  # a facade's re-export, not used by its own code
                paths.append((path, inline))
        # Paths written inline (`crate::service::jobs::PROCESS_FRAME`).
        for match in re.finditer(r"(?<![\w:])(?:crate|super)(?:::\w+)+", text):
            paths.append((match.group(0), depth[match.start()]))
        for path, inline in paths:
            target = resolve(path, module, known, inline)
            if target is None:
                continue
            name = path.split("::")[-1]
            target = through_reexports(target, name, reexports)
            if target != module and target in chosen:
                edges.add((module, target))
                names[(module, target)].add(name)
    up = feedback_arcs(chosen, edges)
    loops = cycles(chosen, edges)
    show = lambda m: str(modules[m].relative_to(ROOT))
    print(f"folders: {', '.join(str(f.relative_to(ROOT)) for f in folders)}")
    print(f"files: {len(chosen)}")
    print(f"arrows: {len(edges)}")
    print(f"arrows pointing back up: {len(up)}")
    print(f"cycles: {len(loops)}" + "".join(f" ({len(c)} files)" for c in loops))
    for component in loops:
        print("  cycle: " + ", ".join(show(m) for m in component))
    for a, b in sorted(up, key=lambda e: (show(e[0]), show(e[1]))):
        print(f"  up: {show(a)} -> {show(b)} ({', '.join(sorted(names[(a, b)]))})")
    if floors:
        folder = folders[0]
        level = {}
        for m in chosen:
            level[m] = floor_of(modules[m], folder, floors)
        against = sorted(
            (show(a), show(b), names[(a, b)])
            for a, b in edges
            if floors.index(level[a]) > floors.index(level[b])
        )
        count = {f: sum(1 for m in chosen if level[m] == f) for f in floors}
        print("floors: " + ", ".join(f"{f} ({count[f]} files)" for f in floors))
        print(f"arrows against the floors: {len(against)}")
        for a, b, n in against:
            print(f"  against: {a} -> {b} ({', '.join(sorted(n))})")


if __name__ == "__main__":
    main()
