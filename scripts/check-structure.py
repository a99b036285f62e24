#!/usr/bin/env python3
"""House rules CI checks on the source text (no build needed):

- no module of a crate imports another that imports it back, directly or around a circle
  (edges: `crate::m` anywhere in top-level module m, `super::m` in its top-level files);
- no function over 80 lines and no file over 600 lines in any crate (tests and benches
  included);
- no `Result<_, String>` anywhere in the workspace.

Prints every offence with its place and exits 1 when there is one. `--graph CRATE` prints the
crate's module graph (the `use` edges) instead.
"""
import os
import re
import sys

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
CRATES = ["settings", "data", "proto", "telemetry", "trainer-core", "worker", "coordinator",
          "evaluation"]
MAX_FUNCTION_LINES = 80
MAX_FILE_LINES = 600
TESTS = re.compile(r"#\[cfg\(test\)\]\s*mod tests\s*\{.*", re.S)
FUNCTION = re.compile(r"^\s*(pub(\([^)]*\))?\s+)?(async\s+)?(const\s+)?(unsafe\s+)?fn\s+(\w+)")


def rust_files(folder):
    for directory, _, names in os.walk(folder):
        for name in sorted(names):
            if name.endswith(".rs"):
                yield os.path.join(directory, name)


def module_graph(crate):
    """Top-level modules of `crate/src` and the modules each one refers to."""
    src = os.path.join(ROOT, crate, "src")
    modules = {}
    for name in os.listdir(src):
        path = os.path.join(src, name)
        if name.endswith(".rs") and name not in ("lib.rs", "main.rs"):
            modules[name[:-3]] = [path]
        elif os.path.isdir(path) and name != "bin":
            modules[name] = list(rust_files(path))
    edges = {module: set() for module in modules}
    for module, files in modules.items():
        for path in files:
            text = TESTS.sub("", open(path).read())
            top = os.path.dirname(path) == src or (
                os.path.basename(path) == "mod.rs"
                and os.path.dirname(os.path.dirname(path)) == src)
            refs = re.findall(r"crate::(\w+)", text)
            refs += re.findall(r"(?<!super::)super::(\w+)", text) if top else re.findall(
                r"super::super::(\w+)", text)
            for group in re.findall(r"use crate::\{([^}]*)\}", text):
                refs += re.findall(r"\b(\w+)\b", group)
            edges[module].update(r for r in refs if r in modules and r != module)
    return edges


def cycles(edges):
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def long_functions(path):
    lines = open(os.path.join(ROOT, path)).read().split("\n")
    if len(lines) > MAX_FILE_LINES:
        yield f"{path}: {len(lines)} lines (at most {MAX_FILE_LINES})"
    for start, line in enumerate(lines):
        match = FUNCTION.match(line)
        if not match:
            continue
        depth, opened, end = 0, False, start
        while end < len(lines):
            code = re.sub(r'"(\\.|[^"\\])*"', '""', lines[end]).split("//")[0]
            code = re.sub(r"'.'", "''", code)
            depth += code.count("{") - code.count("}")
            opened = opened or "{" in code
            if (opened and depth <= 0) or (not opened and code.rstrip().endswith(";")):
                break
            end += 1
        length = end - start + 1
        if length > MAX_FUNCTION_LINES:
            yield f"{path}:{start + 1}: fn {match.group(6)} has {length} lines (at most {MAX_FUNCTION_LINES})"


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "--graph":
        for module, refs in sorted(module_graph(sys.argv[2]).items()):
            print(f"{sys.argv[2]}::{module} -> {', '.join(sorted(refs)) or '(nothing)'}")
        return 0
    offences = []
    for crate in CRATES:
        for cycle in cycles(module_graph(crate)):
            offences.append(f"{crate}: modules import each other around a circle: {' -> '.join(cycle)}")
    for crate in CRATES:
        for path in rust_files(os.path.join(ROOT, crate)):
            offences.extend(long_functions(os.path.relpath(path, ROOT)))
    string_error = re.compile(r"Result<[^;{]*,\s*String>")
    for crate in CRATES:
        for path in rust_files(os.path.join(ROOT, crate)):
            for number, line in enumerate(open(path), 1):
                if string_error.search(line):
                    offences.append(f"{os.path.relpath(path, ROOT)}:{number}: Result<_, String>")
    for offence in offences:
        print(offence)
    print(f"structure: {len(offences)} offence(s) in {len(CRATES)} crates")
    return 1 if offences else 0


if __name__ == "__main__":
    sys.exit(main())
