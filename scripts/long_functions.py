#!/usr/bin/env python3
"""Rust functions longer than a limit, and the longest files.

    python3 scripts/long_functions.py [FOLDER ...] [--over N] [--files M]

Defaults: src, functions over 150 lines, files over 800 lines. A
function runs from its `fn` line to the brace that closes its body
(strings, characters and comments are skipped when braces are counted);
its length counts every line, doc comments excluded. Test modules count
like any code.
"""

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FN = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?fn\s+(\w+)")


def code_only(text: str) -> str:
    """The text with comments, strings and char literals blanked (same
    length and line breaks), so that braces can be counted."""
    out, i, n = [], 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            j = text.find("*/", i + 2)
            j = n if j < 0 else j + 2
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "r" and re.match(r'r#*"', text[i:]) and not re.match(r"\w", text[i - 1 : i] or " "):
            hashes = re.match(r"r(#*)\"", text[i:]).group(1)
            end = '"' + hashes
            j = text.find(end, i + 2 + len(hashes))
            j = n if j < 0 else j + len(end)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            out.append(re.sub(r"[^\n]", " ", text[i : j + 1]))
            i = j + 1
        elif c == "'" and re.match(r"'(\\.|[^\\'])'", text[i : i + 4]) or text.startswith("'\\", i):
            m = re.match(r"'(\\u\{[0-9a-fA-F]+\}|\\.|[^\\'])'", text[i:])
            if m:
                out.append(" " * len(m.group(0)))
                i += len(m.group(0))
            else:
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


def functions(path: Path):
    lines = code_only(path.read_text()).split("\n")
    for start, line in enumerate(lines):
        m = FN.match(line)
        if not m:
            continue
        depth, opened = 0, False
        for end in range(start, len(lines)):
            for ch in lines[end]:
                if ch == "{":
                    depth += 1
                    opened = True
                elif ch == "}":
                    depth -= 1
                elif ch == ";" and not opened and depth == 0:
                    break  # a declaration without a body
            else:
                if opened and depth == 0:
                    yield m.group(1), start + 1, end - start + 1
                    break
                continue
            break


def main():
    args = sys.argv[1:]
    over, files_over = 150, 800
    if "--over" in args:
        i = args.index("--over")
        over = int(args[i + 1])
        args = args[:i] + args[i + 2 :]
    if "--files" in args:
        i = args.index("--files")
        files_over = int(args[i + 1])
        args = args[:i] + args[i + 2 :]
    folders = [ROOT / f for f in (args or ["src"])]
    paths = sorted(p for f in folders for p in ([f] if f.is_file() else f.rglob("*.rs")))
    long = []
    for path in paths:
        for name, line, length in functions(path):
            if length > over:
                long.append((length, f"{path.relative_to(ROOT)}:{line}", name))
    sizes = sorted(
        ((len(p.read_text().split("\n")) - 1, str(p.relative_to(ROOT))) for p in paths), reverse=True
    )
    big = [(n, p) for n, p in sizes if n > files_over]
    print(f"files: {len(paths)}, lines: {sum(n for n, _ in sizes)}")
    print(f"files over {files_over} lines: {len(big)}")
    for n, p in big:
        print(f"  {n:6} {p}")
    print(f"functions over {over} lines: {len(long)}")
    for length, where, name in sorted(long, reverse=True):
        print(f"  {length:6} {name} ({where})")


if __name__ == "__main__":
    main()
