#!/usr/bin/env bash
# Must-have 4 of the serving-core issue, as a matrix: the load benchmark against a fresh default
# `jitdyn serve` at 30, 100 and 400 pendulum_3 sessions offered on a quiet machine, at 60 beside
# one and two CPU hogs (busy loops at nice 0) started before the server, and at 20 with two hogs
# started 12 s into 30-s sessions. Each run's report (admitted, ended, MEASURED, lateness) and the
# reasons of its refusals are printed; the reports, with the server's stall accounts, are kept as
# JSON in the output folder.
#
#   bash benchmarks/promise.sh [OUTPUT_DIR]      # ~4 min; default /tmp/jitdyn-promise
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-/tmp/jitdyn-promise}
mkdir -p "$out"
python=${PYTHON:-.venv/bin/python}
hogs=()
stop_hogs() {
    ((${#hogs[@]})) && kill "${hogs[@]}" 2>/dev/null || true
    hogs=()
}
trap stop_hogs EXIT
hog() { "$python" -c "while True: pass" & hogs+=($!); }

run() { # TAG SESSIONS SECONDS HOGS_BEFORE [SECONDS_TO_TWO_HOGS]
    local tag=$1 sessions=$2 seconds=$3 before=$4 at=${5:-}
    for ((i = 0; i < before; i++)); do hog; done
    ((before)) && sleep 3
    if [[ -n $at ]]; then
        (sleep "$at"; exec "$python" -c "while True: pass") & hogs+=($!)
        (sleep "$at"; exec "$python" -c "while True: pass") & hogs+=($!)
    fi
    "$python" -m benchmarks.load --model pendulum_3 --rate 20 --sessions "$sessions" --seconds "$seconds" \
        --serve-args "--stall-report 15ms" --json "$out/$tag.json" > "$out/$tag.txt" 2>&1 || true
    stop_hogs
    echo "== $tag: $sessions offered, ${seconds} s, $before hogs from the start${at:+, 2 hogs from $at s}"
    grep -v '^  RESOURCE' "$out/$tag.txt" | sed -n 2,6p | grep -v '^WARNING' || true
    grep '^  RESOURCE' "$out/$tag.txt" | cut -c1-110 | sort | uniq -c || true
}

run quiet-30 30 20 0
run quiet-100 100 20 0
run quiet-400 400 20 0
run hog1-60 60 20 1
run hog2-60 60 20 2
run taken-20 20 30 0 12
