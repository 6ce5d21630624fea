#!/usr/bin/env bash
# The tables of docs/results.md: every cell of a protocol trained under the default recipe
# (recipe=cpu), one `python -m train experiment=<cell> protocol=<protocol> seed=<s>` per cell,
# then the cells' per-seed table and the protocol's figure.
#
#   PROTOCOL=airplane SEEDS="0 1 2" scripts/reproduce_recipe.sh
#   PROTOCOL=human CELLS="rpm_cd rpm_ours" SEEDS="0 1 2 3 4" scripts/reproduce_recipe.sh
#   DRY=1 PROTOCOL=real scripts/reproduce_recipe.sh       # print each run's arguments, run nothing
#
# PROTOCOL: airplane, human or real (configs/protocol/, the shared data). CELLS: experiments
# (<rpm|dcp|fmr>_<gt|cd|cdw|ours>) and untrained controls (<rpm|dcp|fmr>_untrained: the initial
# weights evaluated); by default every cell the protocol's table shows. The command is the README's
# cell command as it is (the backbone sizes are the recipe's, configs/recipe_model/); the script
# adds only the machine: one thread each, no progress bars, so two runs share a 2-core machine.
# Finished cells (metrics.json present) are skipped, an interrupted one resumes from its last
# checkpoint. Runs land in $OUT/$PROTOCOL (default outputs/recipe).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-outputs/recipe}
SEEDS=${SEEDS:-0}
PROTOCOL=${PROTOCOL:-airplane}
DRY=${DRY:-0}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}

case $PROTOCOL in
  airplane | human) DEFAULT_CELLS="rpm_gt rpm_cd rpm_ours rpm_untrained dcp_gt dcp_cd dcp_ours dcp_untrained fmr_gt fmr_cd fmr_ours fmr_untrained" ;;
  real) DEFAULT_CELLS="rpm_gt rpm_cd rpm_ours fmr_cd fmr_ours" ;;
  *) echo "reproduce_recipe.sh: error: unknown PROTOCOL '$PROTOCOL' (airplane, human, real)" >&2; exit 2 ;;
esac
CELLS=${CELLS:-$DEFAULT_CELLS}

arguments() {
  local cell=$1 seed=$2 experiment=$1 extra=()
  if [[ $cell == *_untrained ]]; then
    experiment=${cell%_untrained}_ours
    extra+=(trainer.untrained=true)
  fi
  [[ $experiment =~ ^(rpm|dcp|fmr)_(gt|cd|cdw|ours)$ ]] || {
    echo "reproduce_recipe.sh: error: unknown cell '$cell' (<rpm|dcp|fmr>_<gt|cd|cdw|ours|untrained>)" >&2
    return 2
  }
  echo "experiment=$experiment protocol=$PROTOCOL seed=$seed ${extra[*]}"
}

for cell in $CELLS; do arguments "$cell" 0 > /dev/null; done  # unknown cells fail before any run
for seed in $SEEDS; do
  for cell in $CELLS; do
    read -r -a args <<< "$(arguments "$cell" "$seed")"
    if [[ $DRY != 0 ]]; then
      echo "$cell seed=$seed ${args[*]}"
      continue
    fi
    dir=$OUT/$PROTOCOL/${cell}_s$seed
    if [[ -f $dir/metrics.json ]]; then
      echo "done: $dir"
      continue
    fi
    mkdir -p "$OUT/$PROTOCOL"
    [[ -d $dir/checkpoints ]] && args+=(resume=true)
    echo "run: $dir"
    "$PY" -m train "${args[@]}" trainer.threads=1 trainer.progress=false "hydra.run.dir=$dir" >> "$dir.log" 2>&1 \
      || { tail -20 "$dir.log"; exit 1; }
  done
done
[[ $DRY != 0 ]] || "$PY" scripts/reproduce_report.py "$OUT" --write-cells "$OUT/cells.csv" --figures "$OUT"
