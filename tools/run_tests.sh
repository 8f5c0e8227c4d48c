#!/usr/bin/env bash
# The whole test suite (`make test`): setup, the fast pytest suite natively,
# then every rostest on a real SocketCAN vcan0 (natively or inside user-mode
# Linux, see tools/vcan_run.sh), then one summary ending in "N passed, N failed".
#
#   tools/run_tests.sh                 everything
#   tools/run_tests.sh --fast          pytest only
#   tools/run_tests.sh --e2e [PATTERN] rostests only (PATTERN: grep -E on the path)
#   --no-setup                         skip tools/setup.sh (already done)
#   --jobs N                           end-to-end suite in N user-mode Linux at once
#                                      (default: E2E_JOBS, else 2 where the suite runs in
#                                      user-mode Linux and 2 cores are idle, else 1; a
#                                      native vcan0 is one bus, so natively always 1)
set -uo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"

run_fast=1; run_e2e=1; pattern=.; do_setup=1
jobs=${E2E_JOBS:-}
while [ $# -gt 0 ]; do
  case "$1" in
    --fast) run_e2e=0 ;;
    --e2e) run_fast=0; if [ $# -gt 1 ] && [[ "$2" != --* ]]; then pattern=$2; shift; fi ;;
    --no-setup) do_setup=0 ;;
    --jobs) jobs=${2:?--jobs N}; shift ;;
    *) echo "usage: $0 [--fast | --e2e [PATTERN]] [--no-setup] [--jobs N]" >&2; exit 2 ;;
  esac
  shift
done

# The suite's real-time work (SYNC, heartbeats and their consumers, the
# simulated drives' control loops, user-mode Linux's one CPU) has deadlines
# of milliseconds. It runs at a raised priority where the process may (root
# or CAP_SYS_NICE), as a robot runs its driver: other load on the host then
# gets the CPU the suite leaves, instead of stretching its deadlines.
# TEST_NICE=0 runs it at the caller's priority.
test_nice=${TEST_NICE:--10}
if [ "$test_nice" != 0 ]; then
  before=$(nice)
  renice -n "$test_nice" -p $$ >/dev/null 2>&1
  if [ "$(nice)" -lt "$before" ]; then
    echo "test priority: nice $(nice) (TEST_NICE=0 leaves it)"
  else
    echo "test priority: nice $(nice): raising it needs root or CAP_SYS_NICE;" \
         "other load on this host can stretch the real-time tests' deadlines"
  fi
fi

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
  # Test files that mostly wait for ROS processes (roscore, a node, the
  # user's command-line tools) run in a pytest process of their own beside
  # their folder's: the host's cores have work meanwhile.
  beside=(maxon_epos4_ros_canopen/test/unit/test_canopen_motor_node.py
          maxon_epos4_ros_canopen/test/unit/test_compat_cli.py)
  # One pytest process per test folder, or per share of a folder's files
  # for the larger ones (a process per SHARD_FILES files, balanced by the
  # last run's times, tools/pytest_shards.py; a fresh clone by the seed
  # tools/pytest_times.json): test modules of different
  # packages may share a name, and a package folder must never shadow the
  # package. The ROS-free files run again under Python 3.8 (ROS Noetic's),
  # in .venv38 (tools/setup.sh makes it wherever a 3.8 interpreter exists;
  # which files are ROS-free, tools/ros_free_tests.py reads from their
  # imports), split the same way. All of them at once, so that no core
  # idles while a long process ends; each one's output is shown when all
  # are done, with its wall time.
  shard_files=${SHARD_FILES:-25}
  # The searching and the parametrized tests (search_share.py) cover their
  # whole space under the main Python, one case in SEARCH_SHARE_38 under
  # Python 3.8.
  SEARCH_SHARE_38=${SEARCH_SHARE_38:-4}
  times="$results/pytest-times"  # the last run's results: they balance the shares
  mkdir -p "$times"
  if compgen -G "$results/pytest*-*.xml" > /dev/null; then
    rm -f "$times"/*.xml
    for f in "$results"/pytest-*.xml "$results"/pytest38-*.xml; do [ -s "$f" ] && cp "$f" "$times/"; done
  fi
  rm -f "$results"/pytest-*.xml "$results"/pytest38-*.xml "$results"/pytest-*.log "$results"/pytest38-*.log \
        "$results"/pytest-*.time "$results"/pytest38-*.time
  names=(); pids=()
  run_pytest() {  # KIND NAME ARGS...: one pytest process in the background (KIND: pytest or pytest38)
    local kind=$1 name=$2; shift 2
    local xml="$results/$kind-$name.xml" python=.venv/bin/python
    local share=${SEARCH_SHARE:-1}
    [ "$kind" = pytest ] || { python=.venv38/bin/python; share=$SEARCH_SHARE_38; }
    (
      pp="$(IFS=:; echo "${pypath[*]}")"
      # Python 3.8 gets the sources alone: the ROS workspace's modules are 3.11's
      if [ "$kind" = pytest ]; then set +u; . tools/env.sh; set -u; pp="$pp:${PYTHONPATH:-}"; fi
      started=$(date +%s.%N)
      PYTHONPATH="$pp" SEARCH_SHARE="$share" \
        timeout -k 10 1800 "$python" -m pytest -q -p no:cacheprovider --continue-on-collection-errors \
          --junitxml="$xml" "$@"
      rc=$?
      echo "$started $(date +%s.%N)" > "$results/$kind-$name.time"
      exit $rc
    ) > "$results/$kind-$name.log" 2>&1 &
    names+=("$kind-$name"); pids+=($!)
    if [ "$kind" = pytest ]; then report_args+=(--pytest "$xml"); else report_args+=(--pytest38 "$xml"); fi
  }
  run_shares() {  # KIND NAME FILES...: the files in one process per SHARD_FILES of them
    local kind=$1 name=$2; shift 2
    local n=$(( ($# + shard_files - 1) / shard_files )) i=0 line share
    if [ "$n" -le 1 ]; then run_pytest "$kind" "$name" "$@"; return; fi
    while IFS= read -r line; do
      i=$((i + 1))
      read -r -a share <<< "$line"
      [ ${#share[@]} = 0 ] || run_pytest "$kind" "${name}_$i" "${share[@]}"
    done < <(.venv/bin/python tools/pytest_shards.py --shards "$n" --seed tools/pytest_times.json --kind "$kind" \
               $(for f in "$times/$kind-$name".xml "$times/$kind-$name"_[0-9]*.xml; do
                   [ -f "$f" ] && echo --times "$f"; done) "$@")
  }
  for d in "${dirs[@]}"; do
    files=(); own=()
    for f in "$d"/test_*.py; do
      [ -f "$f" ] || continue
      if [[ " ${beside[*]} " == *" $f "* ]]; then own+=("$f"); else files+=("$f"); fi
    done
    name=$(echo "$d" | tr '/' '_')
    [ ${#files[@]} = 0 ] || run_shares pytest "$name" "${files[@]}"
    [ ${#own[@]} = 0 ] || run_pytest pytest "${name}_ros" "${own[@]}"
  done
  if [ -x .venv38/bin/python ]; then
    echo "=== and the ROS-free unit tests under $(.venv38/bin/python -V 2>&1) (.venv38) beside them"
    echo "    (the searching and parametrized tests take one case in ${SEARCH_SHARE_38} there: search_share.py)"
    for d in "${dirs[@]}"; do
      mapfile -t files < <(.venv/bin/python tools/ros_free_tests.py "$d")
      [ ${#files[@]} -gt 0 ] || continue
      run_shares pytest38 "$(echo "$d" | tr '/' '_')" "${files[@]#$REPO/}"
    done
  else
    report_args+=(--python38-absent)
  fi
  for i in "${!pids[@]}"; do
    wait "${pids[$i]}"
    rc=$?
    echo "--- ${names[$i]}"
    cat "$results/${names[$i]}.log"
    # 5 = no tests collected: the report counts a missing or empty run too.
    [ $rc = 0 ] || [ $rc = 1 ] || [ $rc = 5 ] || echo "${names[$i]} exited with status $rc"
  done
  [ -x .venv38/bin/python ] || echo "=== Python 3.8: no .venv38 (tools/setup.sh found no 3.8 interpreter): not run"
  # the wall time of each process, and when each interpreter's last one ended
  .venv/bin/python - "$t_setup" "$results" "${names[@]}" <<'PY'
import sys
t0, results, names = float(sys.argv[1]), sys.argv[2], sys.argv[3:]
ends = {}
for name in names:
    try:
        start, end = (float(x) for x in open("%s/%s.time" % (results, name)).read().split())
    except (OSError, ValueError):
        print("  wall      ?    %s (no time: the process was killed)" % name)
        continue
    print("  wall %6.1f s  %s" % (end - start, name))
    kind = name.split("-", 1)[0]
    ends[kind] = max(ends.get(kind, 0.0), end)
for kind, label in (("pytest", "main Python"), ("pytest38", "Python 3.8")):
    if kind in ends:
        print("fast suite, %s: last process done %.1f s after the start" % (label, ends[kind] - t0))
PY
fi

t_fast=$(date +%s)

if [ $run_e2e = 1 ]; then
  echo "=== end-to-end suite: rostest on vcan0"
  expected=$(ls */test/rostest/*.test 2>/dev/null | grep -cE -- "$pattern")
  # The files' times balance the shards (tools/e2e_group.py --times): each
  # file's from the last run that ran it, and in a fresh clone those of a
  # quiet run committed in tools/e2e_times.
  [ -s "$results/e2e-times" ] || cp tools/e2e_times "$results/e2e-times"
  if [ -s "$results/e2e/manifest" ]; then
    awk 'NR == FNR { seen[$2] = 1; print; next } !($2 in seen)' \
      "$results/e2e/manifest" "$results/e2e-times" > "$results/e2e-times.new" \
      && mv "$results/e2e-times.new" "$results/e2e-times"
  fi
  rm -rf "$results/e2e"
  mkdir -p "$results/e2e"
  transport=$(tools/vcan_run.sh --which)
  if [ -z "$jobs" ]; then
    # user-mode Linux runs one CPU: a second one uses the second core, if
    # that core is idle (a guest that shares its core with other load misses
    # its deadlines; tools/idle_cores.py)
    jobs=1
    if [ "$transport" = uml ] && [ "$(nproc)" -ge 2 ]; then
      jobs=$(.venv/bin/python tools/idle_cores.py --shards 2) || jobs=2
      [ "$jobs" -ge 2 ] || echo "end-to-end suite: under 2 idle cores on this host now: 1 shard (E2E_JOBS=2 forces 2)"
    fi
  elif [ "$transport" = native ] && [ "$jobs" -gt 1 ]; then
    echo "end-to-end suite: native vcan0 is one bus for every shard: --jobs $jobs runs as 1"
    jobs=1
  fi
  [ "$expected" -gt 0 ] || jobs=1
  echo "end-to-end suite: $jobs shard(s) on $transport vcan0"
  if [ "$jobs" -le 1 ]; then
    tools/vcan_run.sh tools/e2e_suite.sh "$results/e2e" "$pattern"
    rc=$?
  else
    # Each shard boots its own user-mode Linux with its own vcan0: the shards
    # share no bus, master or node.
    pids=()
    for i in $(seq 1 "$jobs"); do
      tools/vcan_run.sh tools/e2e_suite.sh "$results/e2e" "$pattern" "$i/$jobs" 2>&1 \
        | sed -u "s|^|[$i/$jobs] |" &
      pids+=($!)
    done
    rc=0
    for p in "${pids[@]}"; do wait "$p" || rc=$?; done
    # vcan_run.sh's status is lost in the pipe: a shard that could not run
    # left no manifest, and the report counts its files as not run.
    cat "$results/e2e"/manifest.* > "$results/e2e/manifest" 2>/dev/null
  fi
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
