#!/usr/bin/env bash
# The end-to-end suite: every rostest of every package, one after the other,
# on the vcan0 that tools/vcan_run.sh provides (natively or in user-mode Linux).
#
#   tools/e2e_suite.sh RESULTS_DIR [PATTERN]
#
# PATTERN (a grep -E expression) selects test files by path. For each test
# file a line "<pkg> <file> <exit status> <seconds>" goes to
# RESULTS_DIR/manifest; rostest's JUnit files go to RESULTS_DIR/xml and its
# output to RESULTS_DIR/logs. tools/testreport.py turns them into the summary.
set -uo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
results=${1:?results dir}
pattern=${2:-.}
cd "$REPO"
# shellcheck disable=SC1091
set +u; . tools/env.sh; set -u

mkdir -p "$results/xml" "$results/logs"
: > "$results/manifest"
echo "--- ip -details link show vcan0"
ip -details link show vcan0
echo "--- python: $(command -v python3) ($(python3 -c 'import can, canopen; print("python-can", can.__version__, "canopen", canopen.__version__)'))"

mapfile -t tests < <(ls */test/rostest/*.test 2>/dev/null | grep -E -- "$pattern" | sort)
echo "--- ${#tests[@]} rostest files"
for t in "${tests[@]}"; do
  pkg=${t%%/*}
  file=$(basename "$t")
  start=$(date +%s.%N)
  # A hard limit per file so one hung test cannot eat CI's 90 minutes.
  timeout -k 10 900 rostest --results-base-dir="$results/xml/$pkg.$file" "$pkg" "$file" device:=vcan0 \
      > "$results/logs/$pkg.$file.log" 2>&1
  rc=$?
  secs=$(python3 -c "import time; print('%.1f' % (time.time() - $start))")
  echo "$pkg $file $rc $secs" >> "$results/manifest"
  if [ $rc = 0 ]; then echo "ok    $pkg/$file (${secs}s)"; else
    echo "FAIL  $pkg/$file (exit $rc, ${secs}s): last lines of its log:"
    tail -25 "$results/logs/$pkg.$file.log" | sed 's/^/      /'
    # The figure lines a test prints as it goes ("fault_matrix: ...") say
    # what happened before the failure, and CI keeps only this output.
    # rostest keeps a test's stdout in its JUnit file.
    figures=$(grep -h -o -E '((fault_matrix|driver_fuzz|mani_fuzz|mani_garbage|sim_fuzz): |controllers \[)[^<]*' \
                -r "$results/xml/$pkg.$file" 2>/dev/null | tail -40 | cut -c1-400 \
              | sed -e "s/&apos;/'/g" -e 's/&quot;/"/g' -e 's/&lt;/</g' -e 's/&gt;/>/g' -e 's/&amp;/\&/g')
    if [ -n "$figures" ]; then
      echo "      --- the figure lines it printed:"
      echo "$figures" | sed 's/^/      /'
    fi
    # The nodes' own warnings and errors (the driver's, the simulator's):
    # what they saw is often the cause, and CI keeps no log directory.
    run_id=$(grep -rho 'run_id\[[^]]*\]' "$results/xml/$pkg.$file" 2>/dev/null | head -1 | sed 's/^run_id\[\(.*\)\]$/\1/')
    if [ -n "$run_id" ]; then
      for node_log in "${ROS_LOG_DIR:-$HOME/.ros/log}/$run_id"/*.log; do
        [ -f "$node_log" ] || continue
        lines=$(grep -E '\]\[(WARNING|ERROR|FATAL)\]' "$node_log" | grep -v ' EMCY 0x' | tail -15 | cut -c1-300)
        if [ -n "$lines" ]; then
          echo "      --- warnings and errors of $(basename "$node_log") (EMCY lines left out), the last 15:"
          echo "$lines" | sed 's/^/      /'
        fi
      done
    fi
  fi
done
exit 0
