#!/usr/bin/env bash
# The whole test suite (`make test`): setup, the fast pytest suite natively,
# then every rostest on a real SocketCAN vcan0 (natively or inside user-mode
# Linux, see tools/vcan_run.sh), then one summary ending in "N passed, N failed".
#
#   tools/run_tests.sh                 everything
#   tools/run_tests.sh --fast          pytest only
#   tools/run_tests.sh --e2e [PATTERN] rostests only (PATTERN: grep -E on the path)
#   --no-setup                         skip tools/setup.sh (already done)
set -uo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"

run_fast=1; run_e2e=1; pattern=.; do_setup=1
while [ $# -gt 0 ]; do
  case "$1" in
    --fast) run_e2e=0 ;;
    --e2e) run_fast=0; if [ $# -gt 1 ] && [[ "$2" != --* ]]; then pattern=$2; shift; fi ;;
    --no-setup) do_setup=0 ;;
    *) echo "usage: $0 [--fast | --e2e [PATTERN]] [--no-setup]" >&2; exit 2 ;;
  esac
  shift
done

t0=$(date +%s)
if [ $do_setup = 1 ]; then
  tools/setup.sh || { echo "setup failed"; echo "0 passed, 1 failed"; exit 1; }
fi
t_setup=$(date +%s)
results="$REPO/.results"
mkdir -p "$results"
report_args=()
status=0

if [ $run_fast = 1 ]; then
  echo "=== fast suite: pytest (ROS-free core, python-can virtual bus)"
  dirs=(); pypath=()
  for d in */test/unit tests/unit; do [ -d "$d" ] && dirs+=("$d"); done
  for d in */src; do [ -d "$d" ] && pypath+=("$REPO/$d"); done
  # One pytest process per test folder: test modules of different packages
  # may share a name, and a package folder must never shadow the package.
  rm -f "$results"/pytest-*.xml
  for d in "${dirs[@]}"; do
    xml="$results/pytest-$(echo "$d" | tr '/' '_').xml"
    (
      set +u; . tools/env.sh; set -u
      PYTHONPATH="$(IFS=:; echo "${pypath[*]}"):${PYTHONPATH:-}" \
        timeout -k 10 1800 .venv/bin/python -m pytest -q -p no:cacheprovider --continue-on-collection-errors --junitxml="$xml" "$d"
    )
    rc=$?
    # 5 = no tests collected: the report counts a missing or empty run too.
    [ $rc = 0 ] || [ $rc = 1 ] || [ $rc = 5 ] || echo "pytest $d exited with status $rc"
    report_args+=(--pytest "$xml")
  done
fi
t_fast=$(date +%s)

if [ $run_e2e = 1 ]; then
  echo "=== end-to-end suite: rostest on vcan0"
  expected=$(ls */test/rostest/*.test 2>/dev/null | grep -cE -- "$pattern")
  rm -rf "$results/e2e"
  tools/vcan_run.sh tools/e2e_suite.sh "$results/e2e" "$pattern"
  rc=$?
  if [ $rc = 3 ]; then
    echo "vcan0 could not be brought up: the end-to-end suite did not run"
    status=1
  fi
  report_args+=(--e2e "$results/e2e" --e2e-expected "$expected")
fi
t_e2e=$(date +%s)

echo "=== summary"
echo "wall time: $((t_e2e - t0)) s (setup $((t_setup - t0)) s, fast $((t_fast - t_setup)) s, end-to-end $((t_e2e - t_fast)) s)"
.venv/bin/python tools/testreport.py "${report_args[@]}" || status=1
exit $status
