#!/usr/bin/env python3
"""Fails when a source file includes what the project's layering forbids (STYLE.md, README's
Layout): an engine including the job layer or the server, worker/io including an engine, anything
under worker/ including gRPC or protobuf, the server including an engine, the renderer or
worker/io (it hands uploads to the job layer unread), the client including more than worker/io
and worker/core, the Python binding including more than the client, the benchmarks including
the tests, a
folder's private header (NAME_internal.h) included from another folder. And the shape rules that
keep modules apart: no product source over 800 lines, no `friend` under worker/ (an engine's
state is an opaque Impl its own files define), no `shared_ptr<void>`, nothing outside
worker/extract naming `extract::internal`, and no class in a worker/jobs header declaring more than
20 member functions (split it into parts with state of their own), and no include cycle among the
modules of worker/jobs (a module is a header with its source; a cycle is reported at the
include that closes it, in the first of its modules by name).

Usage: layering.py [--root DIR]   (DIR: the checkout, default the current directory)
Prints one line per forbidden include (file:line: what it includes, and why not) and exits 1
when there is any.
"""
import argparse
import os
import re
import sys

INCLUDE = re.compile(r'^\s*#\s*include\s*[<"]([^>"]+)[>"]')

# For each folder, the project folders it may include (its own always).
WORKER_BELOW_JOBS = {
    "worker/core": set(),
    "worker/io": {"worker/core"},
    "worker/extract": {"worker/core"},
    "worker/mls": {"worker/core"},
    "worker/render": {"worker/core"},
    "worker/pu": {"worker/core", "worker/extract"},
    "worker/csg": {"worker/core", "worker/extract"},
    "worker/volume": {"worker/core", "worker/extract"},
    "worker/front": {"worker/core", "worker/extract", "worker/mls"},
}
ALLOWED = dict(WORKER_BELOW_JOBS)
ALLOWED["worker/jobs"] = set(WORKER_BELOW_JOBS)
ALLOWED["server"] = {"worker/jobs", "worker/core", "proto"}
ALLOWED["client"] = {"worker/io", "worker/core", "proto"}
# The Python binding is a client: the client library and what it builds on, no engine.
ALLOWED["python"] = {"client", "worker/io", "worker/core", "proto"}
ALLOWED["bench"] = set(ALLOWED) | {"proto", "bench"}
PROJECT_FOLDERS = sorted(set(ALLOWED) | {"proto", "tests", "bench"}, key=len, reverse=True)
# Libraries only the wire layer may see.
WIRE_LIBRARIES = ("grpc", "grpcpp/", "grpc++/", "google/protobuf/")


def folder_of(path):
    for folder in PROJECT_FOLDERS:
        if path == folder or path.startswith(folder + "/"):
            return folder
    return None


MAX_LINES = 800
SHAPE_RULES = (
    (re.compile(r"\bfriend\b"), lambda home: home.startswith("worker/"),
     "no friend under worker/: give the class a constructor from its opaque Impl"),
    (re.compile(r"shared_ptr<void>"), lambda home: True, "no shared_ptr<void>: type it (TypedJobKind)"),
    (re.compile(r"extract::internal"), lambda home: home != "worker/extract",
     "extract::internal is worker/extract's own; use its public API"),
)


MAX_MEMBER_FUNCTIONS = 20
# Classes over the limit until the work that shrinks them lands (none now).
OVERSIZED_FOR_NOW = set()
CLASS_START = re.compile(r"^(?:class|struct)\s+(\w+)\b[^;]*\{\s*$")
# A member function's first line at the class's own indentation: a name followed by "(".
MEMBER_FUNCTION = re.compile(r"^  (?! )(?:[\w:<>,*&~\s]*?\s)?(~?\w+|operator\S+)\s*\(")
# A data member whose type has parentheses (std::function<void()> f_;): not a function.
DATA_MEMBER = re.compile(r"\w+_\s*(?:\{[^}]*\})?;\s*(?://.*)?$")


def oversized_classes(source, lines):
    """Top-level classes declaring more than MAX_MEMBER_FUNCTIONS member functions."""
    found = []
    name, start, count = None, 0, 0
    for number, line in enumerate(lines, 1):
        if name is None:
            match = CLASS_START.match(line)
            if match:
                name, start, count = match.group(1), number, 0
            continue
        if line.startswith("};"):
            if count > MAX_MEMBER_FUNCTIONS and name not in OVERSIZED_FOR_NOW:
                found.append(f"{source}:{start}: class {name} declares {count} member functions: at most "
                             f"{MAX_MEMBER_FUNCTIONS} (split it into parts with state of their own)")
            name = None
            continue
        code = line.split("//", 1)[0]
        if code.lstrip().startswith(("using ", "typedef ")) or DATA_MEMBER.search(code):
            continue
        if MEMBER_FUNCTION.match(code):
            count += 1
    return found


def shape_violations(source, home, lines):
    found = []
    if home == "worker/jobs" and source.endswith(".h"):
        found += oversized_classes(source, lines)
    if len(lines) > MAX_LINES:
        found.append(f"{source}:{len(lines)}: {len(lines)} lines: at most {MAX_LINES} per product source")
    for number, line in enumerate(lines, 1):
        code = line.split("//", 1)[0]
        for pattern, applies, why in SHAPE_RULES:
            if applies(home) and pattern.search(code):
                found.append(f"{source}:{number}: {why}")
    return found


def module_of(source):
    return os.path.splitext(source)[0]


def include_cycles(edges):
    """edges: {module: {included module: (source, line)}}. One line per cycle (a strongly
    connected set of modules), at the include from its first module to another of the set."""
    order, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(module):
        order[module] = low[module] = len(order)
        stack.append(module)
        on_stack.add(module)
        for target in sorted(edges.get(module, ())):
            if target not in order:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], order[target])
        if low[module] == order[module]:
            members = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                members.append(member)
                if member == module:
                    break
            if len(members) > 1:
                cycles.append(sorted(members))

    for module in sorted(edges):
        if module not in order:
            visit(module)
    found = []
    for members in cycles:
        first = members[0]
        target = min(t for t in edges[first] if t in members)
        source, number = edges[first][target]
        names = ", ".join(os.path.relpath(m, "worker/jobs") for m in members)
        found.append(f"{source}:{number}: includes {target}.h: an include cycle among the job modules {names}")
    return found


def violations(root):
    found = []
    job_module_edges = {}
    for top in ("worker", "server", "client", "python", "bench"):
        for directory, _, files in os.walk(os.path.join(root, top)):
            for name in sorted(files):
                if not name.endswith((".h", ".cc")):
                    continue
                path = os.path.join(directory, name)
                source = os.path.relpath(path, root)
                home = folder_of(source)
                if home is None:
                    continue
                with open(path, encoding="utf-8") as f:
                    lines = f.read().split("\n")
                if lines and lines[-1] == "":
                    lines.pop()
                found += shape_violations(source, home, lines)
                for number, line in enumerate(lines, 1):
                    match = INCLUDE.match(line)
                    if not match:
                        continue
                    included = match.group(1)
                    if home == "worker/jobs" and folder_of(included) == "worker/jobs":
                        here, there = module_of(source), module_of(included)
                        if here != there:
                            job_module_edges.setdefault(here, {}).setdefault(there, (source, number))
                    why = judge(home, included)
                    if why:
                        found.append(f"{source}:{number}: includes {included}: {why}")
    return found + include_cycles(job_module_edges)


def judge(home, included):
    if home.startswith("worker/") and included.startswith(WIRE_LIBRARIES):
        return "nothing under worker/ sees gRPC or protobuf"
    target = folder_of(included)
    if target is not None and target != home and included.endswith("_internal.h"):
        return f"{included} is private to {target}"
    if target is None or target == home:
        return None
    if target == "tests":
        return "product code and benchmarks do not include the tests"
    if target not in ALLOWED[home]:
        allowed = ", ".join(sorted(ALLOWED[home])) or "nothing outside itself"
        return f"{home} may include {allowed}"
    return None


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--root", default=".")
    found = violations(parser.parse_args().root)
    for line in found:
        print(line)
    if found:
        print(f"layering: {len(found)} violation(s)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
