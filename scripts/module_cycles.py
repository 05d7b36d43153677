#!/usr/bin/env python3
"""Fails when the modules of a Rust crate import each other in a circle.

A module *uses* another when its file names one of that module's items: `use crate::a::b::X`,
`super::X`, `self::child::f()`, a path like `crate::a::f()` in code, or a child module it declared
(`mod child;` alone is ownership, not use; `pub use child::X` is use). Paths through re-exports
(`pub use`) count as uses of the module that defines the item. Inline modules (`mod tests { ... }`)
belong to their file. Every strongly connected set of more than one module is a circle, printed as
its modules and the lines that make each edge.

Usage: python3 scripts/module_cycles.py CRATE_SRC_DIR [CRATE_SRC_DIR ...]
(e.g. server/service/src). Exit status 1 when any crate has a circle. `--self-test` checks first
that circles put in on purpose are found (and that what is no circle is not reported).
"""

from __future__ import annotations

import re
import sys
from collections import defaultdict
from pathlib import Path

USE = re.compile(r"(?:^|\n)\s*(?:pub(?:\([^)]*\))?\s+)?use\s+([^;]+);")
PATH = re.compile(r"\b((?:crate|super|self)(?:::[A-Za-z_][A-Za-z0-9_]*)+)")
MOD_DECL = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+([A-Za-z_][A-Za-z0-9_]*)\s*;", re.M)


def module_of(src: Path, file: Path) -> tuple[str, ...]:
    """The module path of `file` (`()` for lib.rs/main.rs)."""
    parts = list(file.relative_to(src).with_suffix("").parts)
    if parts[-1] in ("lib", "main", "mod"):
        parts = parts[:-1]
    return tuple(parts)


RENAME = re.compile(r"\s+as\s+([A-Za-z_][A-Za-z0-9_]*)")


def expand(tree: str) -> list[str]:
    """`a::{b, c::{d, e as f}}` as `a::b`, `a::c::d`, `a::c::e` (`as` renames dropped).

    A rename is the word `as` between spaces, so a name that holds the letters (`atlas`,
    `basis`) is kept whole."""
    tree = re.sub(r"\s+", "", RENAME.sub("", tree))
    brace = tree.find("{")
    if brace < 0:
        return [tree]
    prefix, inner = tree[:brace], tree[brace + 1 : tree.rindex("}")]
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(inner):
        depth += ch == "{"
        depth -= ch == "}"
        if ch == "," and depth == 0:
            parts.append(inner[start:i])
            start = i + 1
    parts.append(inner[start:])
    out = []
    for part in parts:
        if part:
            out.extend(prefix + sub for sub in expand(part))
    return out


IDENT_CHAR = re.compile(r"[A-Za-z0-9_]")
RAW_STRING_START = re.compile(r'(?:b|c)?r(#*)"')


def code_only(text: str) -> str:
    """`text` with its comments, string and character literals emptied, line breaks kept.

    A small lexer, not a pattern: a string may hold `//`, `/*`, quotes behind backslashes and
    line breaks (a string continued with `\\` and a new line), a raw string `r#"..."#` may hold
    `"`, block comments nest, and `'a` is a lifetime where `'a'` and `'\\''` are characters.
    Each literal becomes `""` (or `' '`) and each comment a space, so what is left is code."""
    out: list[str] = []
    i, n = 0, len(text)
    while i < n:
        ch, start = text[i], i
        if text.startswith("//", i):
            end = text.find("\n", i)
            i = n if end < 0 else end
            out.append(" ")
            continue
        elif text.startswith("/*", i):
            depth, i = 1, i + 2
            while i < n and depth:
                if text.startswith("/*", i):
                    depth, i = depth + 1, i + 2
                elif text.startswith("*/", i):
                    depth, i = depth - 1, i + 2
                else:
                    i += 1
            out.append(" ")
        elif (raw := RAW_STRING_START.match(text, i)) and (i == 0 or not IDENT_CHAR.match(text[i - 1])):
            close = '"' + raw.group(1)
            end = text.find(close, raw.end())
            i = n if end < 0 else end + len(close)
            out.append('""')
        elif ch == '"':
            i += 1
            while i < n and text[i] != '"':
                i += 2 if text[i] == "\\" else 1
            i += 1
            out.append('""')
        elif ch == "'" and i + 2 < n and (text[i + 1] == "\\" or text[i + 2] == "'"):
            # A character: `'x'` or an escape (`'\\''`, `'\\u{41}'`); `'a` alone is a lifetime.
            i = text.find("'", i + 3 if text[i + 1] == "\\" else i + 2) + 1 or n
            out.append("' '")
        else:
            while i < n and text[i] not in "/\"'rbc":
                i += 1
            if i == start:
                i += 1
            out.append(text[start:i])
            continue
        out.append("\n" * text.count("\n", start, i))
    return "".join(out)


INLINE_MOD = re.compile(r"(?:^|\n)\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+([A-Za-z_][A-Za-z0-9_]*)\s*\{")


def inline_modules(text: str) -> tuple[str, list[tuple[str, str]]]:
    """`text` without its inline modules' bodies, and each inline module's name and body."""
    bodies = []
    while match := INLINE_MOD.search(text):
        depth, i = 1, match.end()
        while depth and i < len(text):
            depth += {"{": 1, "}": -1}.get(text[i], 0)
            i += 1
        bodies.append((match.group(1), text[match.end() : i - 1]))
        text = text[: match.start()] + "\n" + text[i:]
    return text, bodies


def analyse(src: Path) -> list[list[tuple[str, ...]]]:
    files = {module_of(src, f): f for f in sorted(src.rglob("*.rs")) if "bin" not in f.relative_to(src).parts}
    modules = set(files)
    texts: dict[tuple[str, ...], str] = {}
    # Inline modules (`mod tests { ... }`) belong to their file: their paths are read from where
    # they stand (their `super` is the file's module) and their uses count as the file's.
    inline: dict[tuple[str, ...], list[tuple[tuple[str, ...], str]]] = defaultdict(list)
    for m, f in files.items():
        text, bodies = inline_modules(code_only(f.read_text()))
        texts[m] = text
        while bodies:
            name, body = bodies.pop()
            body, nested = inline_modules(body)
            inline[m].append(((*m, name), body))
            bodies.extend(nested)
    children = {m: set(MOD_DECL.findall(t)) for m, t in texts.items()}
    for m, bodies in inline.items():
        for module, body in bodies:
            children[module] = set(MOD_DECL.findall(body))
    # `pub use` re-exports: (module, name) -> the absolute path it stands for.
    reexports: dict[tuple[tuple[str, ...], str], list[str] | None] = {}

    def absolute(module: tuple[str, ...], path: str) -> list[str] | None:
        """`path` as written in `module`, from the crate root; None for another crate."""
        segments = path.split("::")
        if segments[0] == "crate":
            return segments[1:]
        if segments[0] in ("super", "self"):
            base = list(module)
            while segments and segments[0] in ("super", "self"):
                if segments.pop(0) == "super":
                    base = base[:-1]
            return base + segments
        if segments[0] in children[module]:
            return list(module) + segments
        return None

    for module, text in texts.items():
        for match in re.finditer(r"(?:^|\n)\s*pub(?:\([^)]*\))?\s+use\s+([^;]+);", text):
            for path in expand(match.group(1)):
                resolved = absolute(module, path)
                name = path.split("::")[-1]
                alias = RENAME.search(match.group(1))
                if alias and "{" not in match.group(1):
                    name = alias.group(1)
                if name not in ("*", "self"):
                    # None: an item of another crate.
                    reexports[(module, name)] = resolved

    def target(segments: list[str], depth: int = 0) -> tuple[str, ...] | None:
        """The module that defines what `segments` (from the crate root) names."""
        best: tuple[str, ...] = ()
        for i in range(len(segments) + 1):
            if tuple(segments[:i]) in modules:
                best = tuple(segments[:i])
        rest = segments[len(best) :]
        if rest and (best, rest[0]) in reexports and depth < 16:
            again = reexports[(best, rest[0])]
            return None if again is None else target(again + rest[1:], depth + 1)
        return best

    edges: dict[tuple[str, ...], dict[tuple[str, ...], str]] = defaultdict(dict)
    for file_module, text in texts.items():
        for module, body in [(file_module, text), *inline[file_module]]:
            paths = [p for m in USE.finditer(body) for p in expand(m.group(1))]
            paths += PATH.findall(USE.sub("", body))
            for path in paths:
                resolved = absolute(module, path)
                if resolved is None:
                    continue
                to = target(resolved)
                if to is not None and to != file_module and to in modules:
                    edges[file_module].setdefault(to, path)
    return [sorted(c) for c in strongly_connected(modules, edges) if len(c) > 1], edges


def strongly_connected(nodes, edges):  # Tarjan
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
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
            out.append(component)

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def name(module: tuple[str, ...]) -> str:
    return "::".join(module) or "(crate root)"


SELF_TESTS = {
    # name: ({file: text}, circles expected)
    "two modules using each other": (
        {"lib.rs": "mod a;\nmod b;\n", "a.rs": "use crate::b::B;\npub struct A;\n", "b.rs": "pub struct B(crate::a::A);\n"},
        [["a", "b"]],
    ),
    "a child using its parent's item, the parent its child's": (
        {"lib.rs": "pub mod p;\n", "p/mod.rs": "mod c;\npub use c::C;\npub struct P;\n", "p/c.rs": "use super::P;\npub struct C;\n"},
        [["p", "p::c"]],
    ),
    "through a re-export": (
        {"lib.rs": "mod a;\nmod b;\npub use a::A;\n", "a.rs": "use crate::b::B;\npub struct A;\n", "b.rs": "use crate::A;\npub struct B;\n"},
        [["a", "b"]],
    ),
    "a rename is a use of what it renames": (
        {"lib.rs": "mod a;\nmod b;\n", "a.rs": "use crate::b::B as Bee;\npub struct A;\n", "b.rs": "use crate::a::A;\npub struct B;\n"},
        [["a", "b"]],
    ),
    "behind a string continued with a backslash and a new line": (
        {
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": 'pub fn f() -> &\'static str {\n    "one \\\n     two"\n}\nuse crate::b::B;\nconst X: &str = "x";\n',
            "b.rs": "use crate::a::f;\npub struct B;\n",
        },
        [["a", "b"]],
    ),
    "behind raw strings, quote characters and nested comments": (
        {
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": (
                'const R: &str = r#"a "quoted" // word"#;\nconst Q: char = \'"\';\nconst E: char = \'\\\'\';\n'
                "/* outer /* inner */ still a comment */\nfn g<'a>(x: &'a str) -> &'a str { x }\n"
                "use crate::b::B;\nconst S: &str = \"//\";\n"
            ),
            "b.rs": "use crate::a::g;\npub struct B;\n",
        },
        [["a", "b"]],
    ),
    "no circle: a use inside a string, a raw string or a comment is no use": (
        {
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": 'const T: &str = "continued \\\n use crate::b::B;";\nconst U: &str = r#"use crate::b::B;"#;\n/* use crate::b::B; */\n',
            "b.rs": "use crate::a::T;\npub struct B;\n",
        },
        [],
    ),
    "no circle: a sibling whose name holds `as` is not the parent": (
        {
            "lib.rs": "pub mod p;\n",
            "p/mod.rs": "mod atlas;\nmod draw;\npub use draw::D;\n",
            "p/atlas.rs": "pub struct Tile;\n",
            "p/draw.rs": "use super::atlas::Tile;\npub struct D(Tile);\n",
        },
        [],
    ),
    "no circle: siblings over a leaf, inline test modules, another crate's items": (
        {
            "lib.rs": "mod a;\nmod b;\nmod leaf;\npub use std::sync as sync;\n",
            "a.rs": "use crate::leaf::L;\nuse crate::b::B;\n#[cfg(test)]\nmod tests {\n    use super::*;\n}\n",
            "b.rs": "use crate::leaf::L;\nuse crate::sync::Arc;\npub struct B;\n",
            "leaf.rs": "pub struct L;\n",
        },
        [],
    ),
}


def self_test() -> bool:
    """Whether every case of `SELF_TESTS` finds exactly its circles."""
    import tempfile

    good = True
    for name, (files, expected) in SELF_TESTS.items():
        with tempfile.TemporaryDirectory() as folder:
            for path, text in files.items():
                (Path(folder) / path).parent.mkdir(parents=True, exist_ok=True)
                (Path(folder) / path).write_text(text)
            cycles, _ = analyse(Path(folder))
        found = sorted(sorted("::".join(m) for m in c) for c in cycles)
        if found != expected:
            print(f"module_cycles self-test failed: {name}: found {found}, expected {expected}", file=sys.stderr)
            good = False
    return good


def main(argv: list[str]) -> int:
    if argv and argv[0] == "--self-test":
        if not self_test():
            return 1
        print(f"module_cycles: self-test passed ({len(SELF_TESTS)} cases)")
        argv = argv[1:]
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    failed = False
    for arg in argv:
        src = Path(arg)
        if not src.is_dir():
            print(f"module_cycles: {src} is not a directory", file=sys.stderr)
            return 2
        cycles, edges = analyse(src)
        if not cycles:
            print(f"{src}: no module import cycle")
            continue
        failed = True
        for cycle in cycles:
            print(f"{src}: modules that import each other in a circle: {', '.join(name(m) for m in cycle)}")
            members = set(cycle)
            for a in cycle:
                for b, path in sorted(edges[a].items()):
                    if b in members:
                        print(f"    {name(a)} -> {name(b)}   ({path})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
