#!/usr/bin/env bash
# The main job (`make demo`): a simulated EPOS4 moving a joint, no hardware.
# Sets up, then runs tools/demo_session.sh on a real vcan0 (natively where
# the kernel has vcan, otherwise inside user-mode Linux).
set -euo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"
tools/setup.sh
echo "[demo] bringing up vcan0: natively where the kernel has vcan, otherwise by booting user-mode Linux (a few seconds)"
exec tools/vcan_run.sh tools/demo_session.sh
