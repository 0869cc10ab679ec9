#!/usr/bin/env bash
# The README's test command beside N busy loops (default 2, one per core of the CI machine): no test may depend on
# wall-clock speed, so the suite must pass here as it does on a quiet machine (only slower).
#   bash bench/busy_suite.sh [N] [pytest args...]      e.g. bash bench/busy_suite.sh 2 -x
# Prints the pytest summary and a closing line with the wall time and the load; exits with pytest's status.
set -u
cd "$(dirname "$0")/.."
N=${1:-2}
shift $(( $# > 0 ? 1 : 0 ))
pids=()
for _ in $(seq "$N"); do (while :; do :; done) & pids+=($!); done
trap 'kill "${pids[@]}" 2>/dev/null' EXIT
start=$(date +%s)
python3 -m pytest -q tests "$@"
rc=$?
echo "busy_suite: exit $rc in $(( $(date +%s) - start )) s beside $N busy loops; load $(cut -d' ' -f1-3 /proc/loadavg)"
exit $rc
