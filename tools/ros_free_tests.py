#!/usr/bin/env python3
"""List the unit-test files that run without ROS, one path per line.

A test file is ROS-free when neither it nor any module of this repository
that it imports, directly or through other modules, imports a ROS 1 module
(rospy, actionlib, tf2_ros, ...) or generated messages (``*_msgs``,
``*_srvs``, ``PKG.msg``, ``PKG.srv``) when it is loaded: the imports outside
function bodies count (one inside a function runs only when called, as the
guarded rospkg look-up of mani_ros.config does). Imports are read from the
source without running anything, so the list follows the code: a test that
starts to use ROS leaves it by itself.

    ros_free_tests.py FOLDER...   (e.g. */test/unit tests/unit)

tools/run_tests.sh runs these files under Python 3.8 (ROS Noetic's), in
their own virtual environment (.venv38).
"""
from __future__ import annotations

import ast
import glob
import os
import sys
from typing import Dict, Iterator, List, Optional, Set

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROS_MODULES = {
    "rospy", "rostest", "rosunit", "rosgraph", "roslib", "rospkg", "roslaunch", "rosbag", "rosservice",
    "rostopic", "rosnode", "rosparam", "genpy", "genmsg", "catkin", "catkin_pkg", "actionlib", "tf",
    "tf2_ros", "tf2_py", "tf2_geometry_msgs", "diagnostic_updater", "message_filters", "dynamic_reconfigure",
}


def is_ros(module: str) -> bool:
    parts = module.split(".")
    return (parts[0] in ROS_MODULES or parts[0].endswith(("_msgs", "_srvs"))
            or "msg" in parts[1:] or "srv" in parts[1:])


def source_roots() -> List[str]:
    """Where the repository's own modules are found (the pytest.ini pythonpath and more)."""
    return sorted(glob.glob(os.path.join(REPO, "*", "src")) + glob.glob(os.path.join(REPO, "compat", "*", "src")))


def _find(module: str, roots: List[str]) -> Optional[str]:
    rel = module.replace(".", os.sep)
    for root in roots:
        for candidate in (os.path.join(root, rel + ".py"), os.path.join(root, rel, "__init__.py")):
            if os.path.isfile(candidate):
                return candidate
    return None


def _package_of(path: str, roots: List[str]) -> str:
    """The dotted package a file belongs to ('' for a top-level module or a test folder)."""
    for root in roots:
        if path.startswith(root + os.sep):
            rel = os.path.relpath(os.path.dirname(path), root)
            return "" if rel == "." else rel.replace(os.sep, ".")
    return ""


def _load_time_nodes(tree: ast.AST) -> Iterator[ast.AST]:
    """The nodes that run when the module is loaded: all but function bodies."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                todo.append(child)


def imported_modules(path: str, roots: List[str]) -> Iterator[str]:
    """Every module name an import statement of ``path`` run at load time may
    load (``from a import b`` yields a and a.b: b may be a submodule)."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    package = _package_of(path, roots)
    for node in _load_time_nodes(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "importorskip" \
                and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
            yield node.args[0].value  # pytest.importorskip("genpy.generator"): skipped, not run, without ROS
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".") if package else []  # also right for __init__.py
                keep = len(base_parts) - (node.level - 1)
                base = ".".join(base_parts[:max(0, keep)] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base:
                yield base
            for alias in node.names:
                yield "%s.%s" % (base, alias.name) if base else alias.name


def needs_ros(path: str, roots: List[str], memo: Dict[str, bool]) -> bool:
    """True when ``path`` or a repository module it reaches imports ROS."""
    if path in memo:
        return memo[path]
    memo[path] = False  # an import cycle adds nothing new
    local_roots = [os.path.dirname(path)] + roots
    result = False
    for module in imported_modules(path, roots):
        if is_ros(module):
            result = True
            break
        parts = module.split(".")
        # the package's __init__ modules run too
        for i in range(1, len(parts) + 1):
            found = _find(".".join(parts[:i]), local_roots)
            if found is not None and found != path and needs_ros(found, roots, memo):
                result = True
                break
        if result:
            break
    memo[path] = result
    return result


def ros_free(folders: List[str]) -> List[str]:
    roots = source_roots()
    memo: Dict[str, bool] = {}
    files: Set[str] = set()
    for folder in folders:
        files.update(glob.glob(os.path.join(os.path.abspath(folder), "test_*.py")))
    return sorted(f for f in files if not needs_ros(f, roots, memo))


def main(argv: List[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[0], file=sys.stderr)
        print("usage: ros_free_tests.py FOLDER...", file=sys.stderr)
        return 2
    for path in ros_free(argv):
        print(os.path.relpath(path))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
