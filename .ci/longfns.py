#!/usr/bin/env python3
"""Lists the Rust functions longer than a limit, and fails when there is one.

Usage: longfns.py LIMIT DIR...

Every `.rs` file under each DIR is read; each function (a line that starts an item
`fn`, with any of `pub`, `pub(...)`, `const`, `async`, `unsafe`, `extern "..."` before
it) is measured from its `fn` line to the line that closes its body, braces counted
outside comments and string literals; tests are functions too. A declaration without a
body (a trait method ending in `;`) is no function here.

Prints one line per function over LIMIT lines, longest first: `LINES PATH:LINE NAME`.
Exits 1 when any is found, else 0 (printing nothing).
"""

import os
import re
import sys

FN = re.compile(
    r'^\s*(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?(extern\s+"[^"]*"\s+)?fn\s+(\w+)'
)
LINE_COMMENT = re.compile(r"//.*")
STRING = re.compile(r'"(\\.|[^"\\])*"')


def body_end(lines, i):
    """The last line of the function starting at line `i`, and whether it has a body."""
    depth, started = 0, False
    j = i
    while j < len(lines):
        code = STRING.sub('""', LINE_COMMENT.sub("", lines[j]))
        depth += code.count("{") - code.count("}")
        if "{" in code:
            started = True
        if started and depth <= 0:
            break
        if not started and code.rstrip().endswith(";"):
            break
        j += 1
    return j, started


def long_functions(path, limit):
    """(lines, path, first line, name) of each function of `path` over `limit` lines."""
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.read().split("\n")
    found = []
    i = 0
    while i < len(lines):
        m = FN.match(lines[i])
        if m:
            j, started = body_end(lines, i)
            n = j - i + 1
            if started and n > limit:
                found.append((n, path, i + 1, m.group(7)))
            i = j + 1 if started else i + 1
            continue
        i += 1
    return found


def main(argv):
    if len(argv) < 3:
        sys.exit(__doc__)
    limit = int(argv[1])
    found = []
    for folder in argv[2:]:
        for root, _, files in os.walk(folder):
            for name in files:
                if name.endswith(".rs"):
                    found += long_functions(os.path.join(root, name), limit)
    for n, path, line, name in sorted(found, reverse=True):
        print(f"{n} {path}:{line} {name}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
