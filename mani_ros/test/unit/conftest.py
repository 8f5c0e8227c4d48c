"""Makes the package's ROS-free core (src/mani_ros) the module `mani_ros` for pytest.

When pytest runs with --import-mode=importlib and the repository as its root
(tools/run_tests.sh), it names these files `mani_ros.test.unit.*` and
registers the package *folder* mani_ros/ as the module `mani_ros`, which
hides the real package (and makes `mani_ros.config` the config/ folder). The
real package is put back in its place before any test module imports it.
"""
import importlib.util
import os
import sys

_SRC = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "src"))
_PACKAGE = os.path.join(_SRC, "mani_ros")
_INIT = os.path.join(_PACKAGE, "__init__.py")

_present = sys.modules.get("mani_ros")
if _present is None or os.path.normpath(getattr(_present, "__file__", None) or "") != _INIT:
    for _name in [n for n in sys.modules if n.startswith("mani_ros.") and not n.startswith("mani_ros.test")]:
        del sys.modules[_name]   # submodules resolved against the folder, not the package
    _spec = importlib.util.spec_from_file_location("mani_ros", _INIT, submodule_search_locations=[_PACKAGE])
    _package = importlib.util.module_from_spec(_spec)
    sys.modules["mani_ros"] = _package
    _spec.loader.exec_module(_package)
    if _present is not None and hasattr(_present, "test"):
        _package.test = _present.test   # pytest's own modules for these test files
