#!/usr/bin/env bash
# The `make train` figures of the README: the embedded default (`python -m train`, no other
# argument but one thread and no progress bars) from an empty pair cache, timed by
# /usr/bin/time -v; prints its CPU seconds (user + sys, pair generation included), wall time,
# and the test Err_R of the last checkpoint with the validation curve.
#
#   scripts/reproduce_make_train.sh                 # seed 0, run in outputs/make_train
#   SEED=1 OUT=/tmp/mt scripts/reproduce_make_train.sh
#
# With one thread, user + sys approximates the wall time on one quiet core; the default itself
# (trainer.threads=null) uses every core, so on an idle 2-core machine it takes at most that.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-outputs/make_train}
SEED=${SEED:-0}
export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1
run=$OUT/s$SEED
if [[ -e $run ]]; then
  echo "$run exists: remove it to rerun" >&2
  exit 2
fi
mkdir -p "$run"
/usr/bin/time -v -o "$run.time" "$PY" -m train "seed=$SEED" trainer.threads=1 trainer.progress=false \
  "paths.cache_dir=$run/pair_cache" "hydra.run.dir=$run" > "$run.log" 2>&1 || { tail -20 "$run.log"; exit 1; }
"$PY" - "$run" <<'EOF'
import json
import re
import sys
from pathlib import Path

run = Path(sys.argv[1])
timing = Path(f"{run}.time").read_text()
seconds = {key: float(re.search(rf"{key} time \(seconds\): ([0-9.]+)", timing).group(1)) for key in ("User", "System")}
wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", timing).group(1)
metrics = json.loads((run / "metrics.json").read_text())["metrics"]
curve = [
    record["val/err_r_deg_mean"]
    for record in map(json.loads, (run / "scalars.jsonl").read_text().splitlines())
    if "val/err_r_deg_mean" in record
]
print(f"CPU s (user + sys, one thread): {seconds['User'] + seconds['System']:.0f}; wall {wall}")
print(f"test Err_R mean {metrics['test/err_r_deg_mean']:.2f}, median {metrics['test/err_r_deg_median']:.2f} deg "
      f"(identity {metrics['test/identity/err_r_deg_mean']:.2f})")
print("validation Err_R mean per epoch (first: before training):", ", ".join(f"{v:.2f}" for v in curve))
EOF
