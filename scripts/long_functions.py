#!/usr/bin/env python3
"""Lists the project's functions longer than a number of lines (100 by default), longest first.

Rust functions are found on the code alone (comments and string literals emptied by
`module_cycles.code_only`): from the line of `fn` to the line of the brace that closes its body.
Python functions are read with `ast`, from the `def` line to their last line. Nested functions
and closures count inside their function and, for `def`, again on their own. Only the files git
tracks are read; generated code (`*_pb2*.py`) is left out.

Usage: python3 scripts/long_functions.py [--min-lines N] [PATH ...]   (default: the whole repo)
Prints one line per function: `LINES  PATH:LINE  NAME`. Always exits 0: it is a list to read,
not a check.
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from module_cycles import code_only  # noqa: E402

RUST_FN = re.compile(r"\bfn\s+([A-Za-z_][A-Za-z0-9_]*)")


def rust_functions(text: str) -> list[tuple[str, int, int]]:
    """Each function of a Rust file with a body: its name, first line and length in lines."""
    code = code_only(text)
    found = []
    for match in RUST_FN.finditer(code):
        # The body opens at the first `{` after the signature's parentheses, unless a `;` comes
        # first (a declaration in a trait, or a `fn` type).
        depth, i = 0, match.end()
        while i < len(code):
            ch = code[i]
            if ch in "([<":
                depth += 1
            elif ch in ")]>" and not (ch == ">" and code[i - 1] == "-"):
                depth -= 1
            elif depth <= 0 and ch in "{;":
                break
            i += 1
        if i >= len(code) or code[i] == ";":
            continue
        braces, j = 0, i
        while j < len(code):
            braces += {"{": 1, "}": -1}.get(code[j], 0)
            if braces == 0:
                break
            j += 1
        first = code.count("\n", 0, match.start()) + 1
        last = code.count("\n", 0, j) + 1
        found.append((match.group(1), first, last - first + 1))
    return found


def python_functions(text: str) -> list[tuple[str, int, int]]:
    """Each function of a Python file: its qualified name, first line and length in lines."""
    found = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                found.append((name, child.lineno, (child.end_lineno or child.lineno) - child.lineno + 1))
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(text), "")
    return found


def tracked_files(paths: list[str]) -> list[Path]:
    listed = subprocess.run(["git", "ls-files", "--", *paths], capture_output=True, text=True, check=True).stdout
    return [Path(line) for line in listed.splitlines() if line.endswith((".rs", ".py")) and "_pb2" not in line]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--min-lines", type=int, default=100, help="list functions longer than this (default 100)")
    parser.add_argument("paths", nargs="*", help="files or folders (default: the whole repository)")
    args = parser.parse_args(argv)
    rows = []
    for path in tracked_files(args.paths):
        if not path.is_file():
            continue
        text = path.read_text(encoding="utf-8")
        functions = rust_functions(text) if path.suffix == ".rs" else python_functions(text)
        rows.extend((length, f"{path}:{line}", name) for name, line, length in functions if length > args.min_lines)
    for length, where, name in sorted(rows, key=lambda r: (-r[0], r[1])):
        print(f"{length:5}  {where}  {name}")
    print(f"{len(rows)} functions over {args.min_lines} lines", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
