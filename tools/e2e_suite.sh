#!/usr/bin/env bash
# The end-to-end suite: every rostest of every package on the vcan0 that
# tools/vcan_run.sh provides (natively or in user-mode Linux), files that
# start the same nodes against one launch (tools/e2e_group.py).
#
#   tools/e2e_suite.sh RESULTS_DIR [PATTERN [SHARD]]
#
# PATTERN (a grep -E expression) selects test files by path. SHARD "I/N"
# runs the I-th of N parts of about equal time (tools/run_tests.sh --jobs N
# runs N at once, each in its own user-mode Linux), balanced with the times
# of RESULTS_DIR/../e2e-times (each file's time in the last run that ran it,
# see tools/run_tests.sh) when it exists.
# For each test file a line "<pkg> <file> <exit status> <seconds> <group>"
# goes to RESULTS_DIR/manifest (RESULTS_DIR/manifest.I of N for a shard);
# the JUnit files go to RESULTS_DIR/xml and the test nodes' output to
# RESULTS_DIR/logs. tools/testreport.py turns them into the summary.
set -uo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
results=${1:?results dir}
pattern=${2:-.}
shard=${3:-1/1}
manifest="$results/manifest"
[ "$shard" = 1/1 ] || manifest="$results/manifest.${shard%/*}"
cd "$REPO"
# shellcheck disable=SC1091
set +u; . tools/env.sh; set -u

mkdir -p "$results/xml" "$results/logs"
: > "$manifest"
echo "--- ip -details link show vcan0"
ip -details link show vcan0
echo "--- python: $(command -v python3) ($(python3 -c 'import can, canopen; print("python-can", can.__version__, "canopen", canopen.__version__)'))"

mapfile -t tests < <(ls */test/rostest/*.test 2>/dev/null | grep -E -- "$pattern" | sort)
echo "--- ${#tests[@]} rostest files"
# Files whose fixture (nodes and parameters besides the <test>) is the same run
# against one master and one launch (tools/e2e_group.py); every file still gets
# its own results, manifest line and verdict. A hard limit for the whole run so
# one hung group cannot eat CI's 90 minutes (each test also has its own).
timeout -k 30 3000 python3 tools/e2e_group.py "$results" "${tests[@]}" --arg device:=vcan0 \
    --shard "$shard" --times "$results/../e2e-times" --manifest "$manifest" 2>&1 \
  | tee "$results/logs/e2e_group.${shard%/*}.log" | grep --line-buffered -E '^(---|    [A-Za-z0-9_./-]+( \(|: )|ok |FAIL|group .*: (restarted|[0-9]+ files))'
while read -r pkg file rc secs _group; do
  [ "$rc" = 0 ] && continue
  echo "FAIL  $pkg/$file (exit $rc, ${secs}s): last lines of its log:"
  tail -25 "$results/logs/$pkg.$file.log" 2>/dev/null | sed 's/^/      /'
  # The figure lines a test prints as it goes ("fault_matrix: ...") say
  # what happened before the failure, and CI keeps only this output.
  # rostest keeps a test's stdout in its JUnit file.
  figures=$(grep -h -o -E '((fault_matrix|driver_fuzz|mani_fuzz|mani_garbage|sim_fuzz|csp_sync|two_bus): |controllers \[)[^<]*' \
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
done < "$manifest"
exit 0
