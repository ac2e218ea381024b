#!/usr/bin/env bash
# Stability loop (issue 11): the end-to-end suites N times in a row on this machine.
#
#   bench/stability.sh [runs=10] [pytest args...]
#   e.g. bench/stability.sh 10            # test/test_e2e.py test/test_devices_e2e.py
#        bench/stability.sh 5 test/test_operator.py
#
# Each run is a fresh pytest process (its own ROS_DOMAIN_ID, test/conftest.py). Prints one
# line per run (exit code, passed/failed counts, seconds, load average) and a summary; the
# log of every failed run is kept in bench/stability-logs/. Exit code: the number of failed
# runs (0: all passed).
set -uo pipefail
cd "$(dirname "$0")/.."
runs="${1:-10}"
shift || true
tests=("$@")
[ ${#tests[@]} -eq 0 ] && tests=(test/test_e2e.py test/test_devices_e2e.py)
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
    else
        rm -f "$log"
    fi
done
echo "stability: $((runs - failed)) of ${runs} runs passed in $(( $(date +%s) - start )) s"
exit "$failed"
