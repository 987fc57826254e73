#!/usr/bin/env bash
# Repeat CI on a loaded machine: RUNS consecutive `CI=true bash .ci/run` in a
# fresh clone of this repository's HEAD, with BURNERS `python -c "while 1: pass"`
# processes beside them the whole time; stop at the first failure.
#
# This is how "10 consecutive loaded passes" are counted, so anyone can count
# them again. The clone sits in OUT with a `shared` link to the
# checkout's ../shared, exactly as CI lays it out, and gets its own virtualenv;
# the checkout you run it from is not touched. Each run's whole output is kept
# in OUT/run_<i>.log and one line per run goes to OUT/summary.txt: exit status,
# wall time, pytest's summary line and how many real-time runs the suite had
# to try again after a measured scheduler stall (tests/bridge_helpers.py warns
# "runs lost to measured scheduler stalls"; pytest's warnings summary prints the
# message twice, the warning and the source line that raised it, so only the
# "UserWarning:" lines are counted).
#
# Usage: tools/loaded_ci.sh [-n RUNS] [-b BURNERS] [-o OUT] [-c COMMAND]
#   -n RUNS     consecutive runs to try (default 10)
#   -b BURNERS  CPU-burning processes beside them (default 2)
#   -o OUT      working folder: new, empty, or made by this script before (its
#               clone is replaced); default /tmp/qube-loaded-ci
#   -c COMMAND  what one run executes in the clone (default "bash .ci/run")
# Exit status: 0 when every run passed, 1 at the first failed run, 2 on bad usage.
# On a 2-core machine with 2 burners one run took 8 to 20 minutes, depending on
# the day's machine (pytest-xdist on both cores); ten take 1.5 to 3.5 hours.
set -euo pipefail
# The whole script is one brace group ending in exit: bash parses it before it runs
# any of it, so editing or checking out this file during a long loop cannot change
# what the loop runs (bash otherwise reads a script as it goes).
{

RUNS=10
BURNERS=2
OUT=/tmp/qube-loaded-ci
COMMAND="bash .ci/run"
help_text() { sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
while getopts "n:b:o:c:h" opt; do
    case "$opt" in
        n) RUNS=$OPTARG ;;
        b) BURNERS=$OPTARG ;;
        o) OUT=$OPTARG ;;
        c) COMMAND=$OPTARG ;;
        h) help_text; exit 0 ;;
        *) help_text >&2; exit 2 ;;
    esac
done
for value in "$RUNS" "$BURNERS"; do
    if ! [[ "$value" =~ ^[0-9]+$ ]]; then
        echo "loaded_ci: -n and -b take a whole number, got '$value'" >&2
        exit 2
    fi
done

REPO=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
COMMIT=$(git -C "$REPO" rev-parse HEAD)
SHARED=$(cd "$REPO/.." && pwd)/shared
if [ ! -d "$SHARED" ]; then
    echo "loaded_ci: $SHARED: folder not found (CI puts the shared data beside the repository)" >&2
    exit 2
fi
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
# The clone at OUT/main is deleted and made again: never do that to a folder
# this script did not make (OUT could be the folder holding your checkout).
if [ ! -e "$OUT/.loaded_ci" ] && [ -n "$(ls -A "$OUT")" ]; then
    echo "loaded_ci: $OUT: not empty and not made by loaded_ci; choose a new folder (-o)" >&2
    exit 2
fi
touch "$OUT/.loaded_ci"
CLONE="$OUT/main"
rm -rf "$CLONE"
git clone -q "$REPO" "$CLONE"
git -C "$CLONE" checkout -q "$COMMIT"
ln -sfn "$SHARED" "$OUT/shared"
[ -x "$OUT/venv/bin/python" ] || python3 -m venv "$OUT/venv"
# shellcheck disable=SC1091
source "$OUT/venv/bin/activate"

pids=()
cleanup() { [ ${#pids[@]} -eq 0 ] || kill "${pids[@]}" 2>/dev/null || true; }
trap cleanup EXIT
trap 'exit 130' INT TERM
for _ in $(seq 1 "$BURNERS"); do
    python3 -c "while 1: pass" &
    pids+=("$!")
done

SUMMARY="$OUT/summary.txt"
echo "$(date -u +%FT%TZ) commit ${COMMIT:0:7}, $RUNS runs, $BURNERS burners on $(nproc) cores: $COMMAND" \
    | tee -a "$SUMMARY"
for i in $(seq 1 "$RUNS"); do
    log="$OUT/run_$i.log"
    start=$(date +%s)
    rc=0
    (cd "$CLONE" && CI=true bash -c "$COMMAND" < /dev/null) > "$log" 2>&1 || rc=$?
    elapsed=$(( $(date +%s) - start ))
    result=$(grep -E '^[0-9]+ (passed|failed|errors?|skipped)|no tests ran' "$log" | tail -n 1 || true)
    retries=$(grep -c "UserWarning: runs lost to measured scheduler stalls" "$log" || true)
    printf 'run %d: exit %d, %d:%02d, %s, real-time retries %d\n' \
        "$i" "$rc" $((elapsed / 60)) $((elapsed % 60)) "${result:-no pytest summary}" "$retries" \
        | tee -a "$SUMMARY"
    if [ "$rc" -ne 0 ]; then
        echo "failed at run $i of $RUNS: see $log" | tee -a "$SUMMARY"
        exit 1
    fi
done
echo "all $RUNS runs passed" | tee -a "$SUMMARY"
exit 0
}
