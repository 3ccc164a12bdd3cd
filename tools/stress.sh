#!/usr/bin/env bash
# The real-time tests under load: runs the timing phase (pytest -m "timing or realtime": every test
# that runs a real-time loop) N times while K busy loops take the cores, and prints how many of the N
# runs each test passed.
#
#   tools/stress.sh [N] [K] [extra pytest args ...]      (defaults: N=10, K=2)
#   make stress STRESS_N=10 STRESS_K=2
#
# A test that asserts on wall-clock windows fails here first: every real-time test should pass N of N.
# Each run's JUnit XML and output go to $STRESS_OUT/<stamp>/ (default build/stress; a new directory
# per call, nothing else is written). Exit 0 when every test passed every run, 1 otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."
N=${1:-10}
K=${2:-2}
shift $(( $# >= 2 ? 2 : $# ))
case "$N$K" in *[!0-9]*) echo "stress.sh: N and K are whole numbers (runs, busy loops); got N=$N K=$K" >&2; exit 2 ;; esac
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || { echo "stress.sh: $PY not found: run 'make install-dev' first (or set PYTHON)" >&2; exit 2; }
out="${STRESS_OUT:-build/stress}/$(date -u +%Y%m%dT%H%M%SZ)-$$"
mkdir -p "$(dirname "$out")"
mkdir "$out"

busy=()
stop_busy() { for p in "${busy[@]:-}"; do [ -n "$p" ] && kill "$p" 2>/dev/null || true; done; }
trap stop_busy EXIT
for _ in $(seq 1 "$K"); do
  ( trap 'exit 0' TERM; while :; do :; done ) &
  busy+=($!)
done
echo "stress: $N runs of the real-time tests with $K busy loops on $(nproc) cores -> $out"
for i in $(seq 1 "$N"); do
  start=$(date +%s)
  set +e
  "$PY" -m pytest -q -p no:cacheprovider -m "timing or realtime" --junitxml="$out/run$i.xml" "$@" > "$out/run$i.log" 2>&1
  rc=$?
  set -e
  echo "run $i/$N: exit $rc in $(( $(date +%s) - start )) s: $(tail -n 1 "$out/run$i.log")"
done
stop_busy
trap - EXIT
"$PY" - "$out" "$N" <<'EOF'
import sys, glob
import xml.etree.ElementTree as ET
from collections import defaultdict

out, n = sys.argv[1], int(sys.argv[2])
passed, seen = defaultdict(int), defaultdict(int)
why = defaultdict(list)
for f in sorted(glob.glob(f"{out}/run*.xml")):
    for tc in ET.parse(f).getroot().iter("testcase"):
        name = f"{tc.get('classname', '').rsplit('.', 1)[-1]}::{tc.get('name')}"
        seen[name] += 1
        bad = [c for c in tc if c.tag in ("failure", "error", "skipped")]
        if bad:
            why[name].append((bad[0].get("message") or bad[0].tag).splitlines()[0][:150])
        else:
            passed[name] += 1
width = max(map(len, seen), default=10)
print(f"\n{'test':<{width}}  passed / runs")
for name in sorted(seen):
    print(f"{name:<{width}}  {passed[name]:>6} / {n}")
    for w in why[name]:
        print(f"{'':<{width}}    {w}")
ok = seen and all(passed[k] == n for k in seen)
sys.exit(0 if ok else 1)
EOF
