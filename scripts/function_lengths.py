#!/usr/bin/env python3
"""Fails when a function in the product (worker/ server/ client/ bench/) is longer than the limit.

A function is a brace block whose opening line closes a parameter list (`) {`, `) const {`,
`) override {` ...) and is not a control statement; its length counts every line from that
opening line to the matching closing brace. Comments and string literals are blanked first so
that their braces do not count. Usage: function_lengths.py [--limit N] [DIR...]
"""
import argparse
import os
import re
import sys

SIGNATURE = re.compile(r"\)\s*(const\s*)?(override\s*)?(noexcept\s*)?(->\s*[\w:<>,\s*&]+)?\{\s*$")
CONTROL = re.compile(r"^\s*(\}\s*)?(if|for|while|switch|else|do|catch)\b")


def blank_literals(text):
    text = re.sub(r"/\*.*?\*/", lambda m: re.sub(r"[^\n]", " ", m.group(0)), text, flags=re.S)
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r'R"(\w*)\((.*?)\)\1"', lambda m: re.sub(r"[^\n]", " ", m.group(0)), text, flags=re.S)
    text = re.sub(r'"(\\.|[^"\\\n])*"', '""', text)
    return re.sub(r"'(\\.|[^'\\\n])*'", "''", text)


def functions(path):
    lines = blank_literals(open(path, encoding="utf-8").read()).split("\n")
    depth, start, start_depth = 0, None, 0
    for number, line in enumerate(lines, 1):
        for column, ch in enumerate(line):
            if ch == "{":
                if start is None and SIGNATURE.search(line[: column + 1]) and not CONTROL.match(line):
                    start, start_depth = number, depth
                depth += 1
            elif ch == "}":
                depth -= 1
                if start is not None and depth == start_depth:
                    yield start, number - start + 1
                    start = None


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--limit", type=int, default=120)
    parser.add_argument("dirs", nargs="*", default=["worker", "server", "client", "bench"])
    args = parser.parse_args()
    too_long = []
    for root in args.dirs:
        for folder, _, names in os.walk(root):
            for name in sorted(names):
                if name.endswith((".cc", ".h")):
                    path = os.path.join(folder, name)
                    too_long += [(n, path, line) for line, n in functions(path) if n > args.limit]
    for n, path, line in sorted(too_long, reverse=True):
        print(f"{path}:{line}: function of {n} lines (limit {args.limit})")
    return 1 if too_long else 0


if __name__ == "__main__":
    sys.exit(main())
