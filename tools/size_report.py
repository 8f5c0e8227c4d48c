#!/usr/bin/env python3
"""Files and classes over the size limits (issue 24: no class over 500 lines,
no file over 600), with the largest of each for scale.

    python3 tools/size_report.py [DIR ...]   (default: maxon_epos4_ros_canopen/src)

Exits 1 when something is over a limit.
"""
import ast
import os
import sys

FILE_LIMIT = 600
CLASS_LIMIT = 500


def sizes(root: str):
    """(path, lines, [(class, lines)]) of every .py file under root."""
    for folder, _, names in os.walk(root):
        for name in sorted(names):
            if not name.endswith(".py"):
                continue
            path = os.path.join(folder, name)
            with open(path, encoding="utf-8") as f:
                text = f.read()
            classes = [(node.name, node.end_lineno - node.lineno + 1) for node in ast.walk(ast.parse(text))
                       if isinstance(node, ast.ClassDef)]
            yield path, len(text.splitlines()), classes


def main() -> int:
    roots = sys.argv[1:] or ["maxon_epos4_ros_canopen/src"]
    files, classes = [], []
    for root in roots:
        for path, lines, cls in sizes(root):
            files.append((lines, path))
            classes.extend((n, "%s:%s" % (path, name)) for name, n in cls)
    files.sort(reverse=True)
    classes.sort(reverse=True)
    over_files = [f for f in files if f[0] > FILE_LIMIT]
    over_classes = [c for c in classes if c[0] > CLASS_LIMIT]
    print("files over %d lines: %d" % (FILE_LIMIT, len(over_files)))
    for lines, path in over_files:
        print("  %5d %s" % (lines, path))
    print("classes over %d lines: %d" % (CLASS_LIMIT, len(over_classes)))
    for lines, name in over_classes:
        print("  %5d %s" % (lines, name))
    print("largest files:")
    for lines, path in files[:5]:
        print("  %5d %s" % (lines, path))
    print("largest classes:")
    for lines, name in classes[:5]:
        print("  %5d %s" % (lines, name))
    return 1 if over_files or over_classes else 0


if __name__ == "__main__":
    sys.exit(main())
