#!/usr/bin/env bash
# Stability loop (issue 11): the end-to-end suites N times in a row on this machine.
#
#   bench/stability.sh [runs=10] [pytest args...]
#   e.g. bench/stability.sh 10            # the e2e suites and the operator soak, full length
#        bench/stability.sh 5 test/test_operator.py
#
# The soaks run at full length here (issue 26): the suite runs the first 6 goals of each
# seeded random-goal soak and the first 12 actions of the seeded random operator
# (BRACE_OPERATOR_ACTIONS); this script the 20 goals (BRACE_SOAK_GOALS) and 60 s of the
# operator (BRACE_OPERATOR_SECONDS: set, it runs that long: 74 actions), same seeds, same
# checks. Run it and record it in bench/RESULTS.md before a stop that touches the execution
# path. The operator soak alone, its summary line kept:
#
#   STABILITY_KEEP_LOGS=1 bench/stability.sh 1 -s test/test_operator_property.py
#   grep '^seed' bench/stability-logs/run-1.log
#
# Each run is a fresh pytest process (its own ROS_DOMAIN_ID, test/conftest.py). Prints one
# line per run (exit code, passed/failed counts, seconds, load average) and a summary; the
# log of every failed run is kept in bench/stability-logs/ (of every run with
# STABILITY_KEEP_LOGS=1). Exit code: the number of failed runs (0: all passed).
set -uo pipefail
cd "$(dirname "$0")/.."
runs="${1:-10}"
shift || true
tests=("$@")
[ ${#tests[@]} -eq 0 ] && tests=(test/test_e2e.py test/test_devices_e2e.py test/test_operator_property.py)
export BRACE_SOAK_GOALS="${BRACE_SOAK_GOALS:-20}"
export BRACE_OPERATOR_SECONDS="${BRACE_OPERATOR_SECONDS:-60}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
py=.venv/bin/python
[ -x "$py" ] || py=python3
logs=bench/stability-logs
mkdir -p "$logs"
failed=0
start=$(date +%s)
echo "stability: ${runs} runs of ${tests[*]} on $(nproc) CPUs, $(date -u +%FT%TZ)"
for i in $(seq 1 "$runs"); do
    log="$logs/run-$i.log"
    t0=$(date +%s)
    "$py" -m pytest -q -p no:cacheprovider "${tests[@]}" >"$log" 2>&1
    rc=$?
    t1=$(date +%s)
    summary=$(grep -E '[0-9]+ (passed|failed)' "$log" | tail -1)
    printf 'run %2d: exit %d, %s, %d s, load %s\n' "$i" "$rc" "${summary:-no summary}" \
        "$((t1 - t0))" "$(cut -d' ' -f1-3 /proc/loadavg)"
    if [ "$rc" -ne 0 ]; then
        failed=$((failed + 1))
        grep -E '^(FAILED|ERROR)' "$log" | sed 's/^/        /'
    elif [ -z "${STABILITY_KEEP_LOGS:-}" ]; then
        rm -f "$log"
    fi
done
echo "stability: $((runs - failed)) of ${runs} runs passed in $(( $(date +%s) - start )) s"
exit "$failed"
