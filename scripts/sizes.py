#!/usr/bin/env python3
"""File and function sizes of ptv's Rust sources, to check a restructuring
before and after it.

    python3 scripts/sizes.py [FOLDER ...]                  # default: src
    python3 scripts/sizes.py src --files 800 --functions 150

It prints a summary (files, lines, functions, the largest of each) and
lists the files over `--files` lines (default 800) and the functions over
`--functions` lines (default 150), largest first. Lines are the file's
lines, comments and blank lines included, as `wc -l` counts them. A
function runs from its `fn` line to the brace that closes its body; braces
in strings, character literals and comments are skipped, which is enough
for rustfmt-formatted code (a raw string holding an unbalanced brace would
mislead it: the script says so if a file's braces do not balance). Test
modules count like the rest (`#[cfg(test)]` code is code a reader reads).
"""

import argparse
import os
import re
import sys

FN = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?fn\s+(\w+)")


def strip_line(line, state):
    """The line with string, char and comment contents removed; `state`
    carries an open block comment or string across lines."""
    out = []
    i, n = 0, len(line)
    while i < n:
        if state["block"]:
            end = line.find("*/", i)
            if end < 0:
                return "".join(out)
            state["block"] = False
            i = end + 2
            continue
        if state["string"]:
            if line[i] == "\\":
                i += 2
                continue
            if line[i] == '"':
                state["string"] = False
            i += 1
            continue
        c = line[i]
        if line.startswith("//", i):
            break
        if line.startswith("/*", i):
            state["block"] = True
            i += 2
            continue
        if c == '"':
            state["string"] = True
            i += 1
            continue
        if c == "'":
            # A char literal ('x', '\n', '{') or a lifetime ('a).
            m = re.match(r"'(\\.|[^\\'])'", line[i:])
            if m:
                i += len(m.group(0))
                continue
        out.append(c)
        i += 1
    return "".join(out)


def functions(path):
    """(name, first line, line count) of each function in the file."""
    with open(path, encoding="utf-8") as f:
        lines = f.read().split("\n")
    state = {"block": False, "string": False}
    found, open_fns = [], []
    depth = 0
    for number, raw in enumerate(lines, 1):
        code = strip_line(raw, state)
        m = FN.match(code)
        if m:
            open_fns.append([m.group(1), number, None])
        for c in code:
            if c == "{":
                depth += 1
                if open_fns and open_fns[-1][2] is None:
                    open_fns[-1][2] = depth
            elif c == "}":
                if open_fns and open_fns[-1][2] == depth:
                    name, start, _ = open_fns.pop()
                    found.append((name, start, number - start + 1))
                depth -= 1
            elif c == ";" and open_fns and open_fns[-1][2] is None:
                open_fns.pop()  # a declaration without a body (a trait's)
    if depth != 0:
        print(f"warning: {path}: braces do not balance ({depth})", file=sys.stderr)
    return len(lines) - (1 if lines and lines[-1] == "" else 0), found


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folders", nargs="*", default=["src"])
    parser.add_argument("--files", type=int, default=800)
    parser.add_argument("--functions", type=int, default=150)
    args = parser.parse_args()
    files, fns = [], []
    for folder in args.folders:
        for root, _, names in os.walk(folder):
            for name in sorted(names):
                if name.endswith(".rs"):
                    path = os.path.join(root, name)
                    count, found = functions(path)
                    files.append((count, path))
                    fns.extend((length, path, start, fname) for fname, start, length in found)
    files.sort(reverse=True)
    fns.sort(reverse=True)
    total = sum(c for c, _ in files)
    print(f"{len(files)} files, {total} lines, {len(fns)} functions")
    big_files = [f for f in files if f[0] > args.files]
    big_fns = [f for f in fns if f[0] > args.functions]
    print(f"files over {args.files} lines: {len(big_files)}")
    for count, path in big_files:
        print(f"  {count:6d} {path}")
    print(f"functions over {args.functions} lines: {len(big_fns)}")
    for length, path, start, name in big_fns:
        print(f"  {length:6d} {path}:{start} {name}")


if __name__ == "__main__":
    main()
