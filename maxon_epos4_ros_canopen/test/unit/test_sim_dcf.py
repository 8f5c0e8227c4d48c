"""The project's DCFs (from tools/make_epos4_dcf.py) and maxon's exports all
serve as virtual EPOS4s; the generated files are up to date."""
import glob
import os
import subprocess
import sys

import canopen
import pytest

from sim_support import CONFIG, VENDOR_DIR, NodeConfig, enable

REPO = os.path.dirname(os.path.dirname(CONFIG))
VENDOR_FILES = sorted(glob.glob(os.path.join(VENDOR_DIR, "*.dcf")))


def test_generated_dcfs_are_current():
    result = subprocess.run([sys.executable, os.path.join(REPO, "tools", "make_epos4_dcf.py"), "--check"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("name, method", [("epos4_node1.dcf", 0), ("epos4_node2.dcf", 0),
                                          ("epos4_node1_hm.dcf", -3)])
def test_project_dcfs(name, method):
    od = canopen.import_od(os.path.join(CONFIG, name))
    assert od[0x6098].value == method
    assert od[0x60C2][1].value == 10
    assert od[0x2200][2].data_type == 0x1  # BOOLEAN kept
    assert od[0x1600][2].value == 0x60FF0020 and od[0x1A02][2].value == 0x30D30120


@pytest.mark.skipif(not VENDOR_FILES, reason="maxon's DCFs are test data in ../shared/vendor_dcf, "
                                             "absent outside the project's machines")
@pytest.mark.parametrize("path", VENDOR_FILES, ids=[os.path.basename(p) for p in VENDOR_FILES])
def test_vendor_dcf_serves_ppm_move(path, sim_rig):
    node_id = canopen.import_od(path).node_id or 1
    rig = sim_rig([NodeConfig(node_id, path)])
    try:
        node = rig.remote(node_id, path)
        assert node.sdo[0x1018][1].raw == 0xFB
        enable(node, 1)
        start = node.sdo[0x6064].raw
        node.sdo[0x607A].raw = start + 3000
        node.sdo[0x6040].raw = 0x001F
        node.sdo[0x6040].raw = 0x000F
        assert rig.wait(lambda: node.sdo[0x6041].raw & 0x0400 and node.sdo[0x6062].raw == start + 3000)
        assert abs(node.sdo[0x6064].raw - (start + 3000)) < 200
    finally:
        rig.close()


def test_dcf_missing_gives_clear_error(sim_rig):
    with pytest.raises(Exception):
        sim_rig([NodeConfig(1, os.path.join(CONFIG, "no_such.dcf"))])
