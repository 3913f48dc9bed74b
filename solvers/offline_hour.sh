#!/bin/bash
# An hour of a 48-robot cell, offline (issue 31): record, solve on 2 workers (with a journal),
# the same on Ray, then --compare (the windows read back from the journal), each under
# /usr/bin/time -v and with the process tree's memory sampled; then the results file.
#
#   nohup solvers/offline_hour.sh /work/runs/hour > /work/runs/hour/run.log 2>&1 &
#
# Writes DIR/{record,solve,ray,compare}.{json,time}, DIR/steps.log, DIR/treerss.csv and
# DIR/hour48.parquet (about 15 MB: keep it out of the repository), then
# docs/results/offline_hour.json (python solvers/offline_hour.py summarize DIR).
set -u
DIR=${1:?usage: offline_hour.sh DIR}
REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-$REPO/.venv/bin/python}
C=${CODESIGN:-$REPO/.venv/bin/codesign}
mkdir -p "$DIR" && cd "$DIR" || exit 1
T=hour48.parquet
J=hour48.windows.jsonl
cat > commands.txt <<CMDS
codesign wifi trace $T --robots 48 --steps 90000 --channel paper -q 0.1 --seed 0 --json
codesign solve $T --workers 2 --journal $J --json
codesign solve $T --workers 2 --backend ray --json
codesign solve $T --workers 2 --journal $J --compare --json
CMDS
date -Is > steps.log
"$PY" "$REPO/solvers/offline_hour.py" sample $$ treerss.csv steps.log &
run() {  # STEP ARGS...: one command of commands.txt, timed
    local step=$1
    shift
    echo "$step $(date -Is)" >> steps.log
    /usr/bin/time -v "$C" "$@" > "$step.json" 2> "$step.time"
    echo "$step rc=$? $(date -Is)" >> steps.log
}
rm -f "$J"
run record wifi trace $T --robots 48 --steps 90000 --channel paper -q 0.1 --seed 0 --json
run solve solve $T --workers 2 --journal $J --json
run ray solve $T --workers 2 --backend ray --json
run compare solve $T --workers 2 --journal $J --compare --json
"$PY" "$REPO/solvers/offline_hour.py" summarize . --out "$REPO/docs/results/offline_hour.json"
