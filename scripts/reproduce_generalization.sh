#!/usr/bin/env bash
# The trainings behind docs/results.md's generalization tables, then their scores:
#
#   scripts/reproduce_generalization.sh                                   # every step, seeds 0 1 2
#   STEPS=unseen_body CELLS="rpm_cd rpm_ours" SEEDS=0 scripts/reproduce_generalization.sh
#   DRY=1 scripts/reproduce_generalization.sh                             # print each run, run nothing
#
# STEPS:
#   unseen_body  Human, leave one body out: each cell trained on two bodies and tested on the third,
#                one run per held-out body (configs/dataset/human_unseen_body.yaml);
#   mixed_pairs  Airplane with both pair types in training, view-vs-view and view-vs-whole at the
#                budget of one (configs/dataset/airplane_mixed_pairs.yaml);
#   human_choice   RPM-Ours on Human at the line loss's other settings (nu0 0.5 / 2, 5000 / 20 000
#                lines; the recipe's nu0 = 2 with 20 000 lines is the protocol's own cell);
#   objects      the general model: RPM-Net on every object of the shared data, both pair types
#                (configs/dataset/objects.yaml), with the line loss and with Chamfer (rpm_cd and
#                rpm_ours of CELLS);
#   rooms        the general model with the Real protocol's room frames too
#                (configs/dataset/objects_and_rooms.yaml: easy pairs 6 frames apart), with the
#                rooms at the test pairs' 20 frames throughout, and with the Real protocol's second
#                stage after it at 20 frames apart (the Airplane curriculum's `full` stage at a
#                variant of objects_and_rooms.yaml): 4 epochs of the room frames alone, or 2 of the
#                rooms beside the objects (rpm_cd and rpm_ours of CELLS);
#   real_choice  Real without its easier pairs first: every stage at the test pairs' gap of 20
#                frames (the recipe's curriculum, re-chosen on validation pairs; rpm_cd, rpm_ours);
#   dcp_choice   DCP on Airplane without its full-range stage: 4 epochs of easy poses only (the recipe's
#                stage, re-chosen on validation pairs; DCP's twins of the cd and ours cells of CELLS;
#                the recipe's runs: STEPS=seeds CELLS="dcp_cd dcp_ours" PROTOCOLS=airplane);
#   human_stretch  Human with its training pairs stretched per axis by up to 20 % (anisotropic_scale,
#                validation and test pairs as they are; rpm_cd, rpm_ours);
#   seeds        the cells of PROTOCOLS (default airplane human real) themselves at PROTOCOL_SEEDS
#                (default 1 2: seed 0 is the shipped RPM-Net), for their generalization splits (as
#                scripts/reproduce_recipe.sh, into $OUT/recipe/<protocol>/); the FMR and DCP rows:
#                STEPS=seeds CELLS="fmr_cd fmr_ours" PROTOCOL_SEEDS="0 1 2".
# Each run is the README's cell command with a dataset choice (and the same machine arguments as
# scripts/reproduce_recipe.sh: one thread, no progress bars). Finished runs (metrics.json present)
# are skipped, an interrupted one resumes. Runs land in $OUT/<step>/...; the scores of every run and
# of the shipped networks go to $OUT/scores (scripts/score_generalization.py).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-outputs/generalization_runs}
SEEDS=${SEEDS:-0 1 2}
CELLS=${CELLS:-rpm_gt rpm_cd rpm_ours}
STEPS=${STEPS:-unseen_body mixed_pairs human_choice objects rooms real_choice dcp_choice human_stretch seeds}
PROTOCOL_SEEDS=${PROTOCOL_SEEDS:-1 2}
PROTOCOLS=${PROTOCOLS:-airplane human real}
BODIES="human_man human_neutral human_woman"
DRY=${DRY:-0}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}

# "<run folder> <arguments>" of every run of a step
runs() {
  local step=$1 seed cell body protocol
  if [[ $step == seeds ]]; then
    for seed in $PROTOCOL_SEEDS; do
      for protocol in $PROTOCOLS; do
        for cell in $CELLS; do
          echo "$OUT/recipe/$protocol/${cell}_s$seed experiment=$cell protocol=$protocol seed=$seed"
        done
      done
    done
    return
  fi
  for seed in $SEEDS; do
    for cell in $CELLS; do
      case $step in
        unseen_body)
          for body in $BODIES; do
            echo "$OUT/unseen_body/$body/${cell}_s$seed experiment=$cell protocol=human dataset=human_unseen_body dataset.held_out=$body seed=$seed"
          done ;;
        mixed_pairs)
          echo "$OUT/mixed_pairs/${cell}_s$seed experiment=$cell protocol=airplane dataset=airplane_mixed_pairs seed=$seed" ;;
        objects)
          [[ $cell == rpm_gt ]] && continue
          echo "$OUT/objects/${cell}_s$seed experiment=$cell protocol=airplane dataset=objects task_name=${cell}_objects seed=$seed" ;;
        rooms)
          [[ $cell == rpm_gt ]] && continue
          echo "$OUT/objects_and_rooms/${cell}_s$seed experiment=$cell protocol=airplane dataset=objects_and_rooms task_name=${cell}_objects seed=$seed"
          echo "$OUT/objects_and_rooms_gap20/${cell}_s$seed experiment=$cell protocol=airplane dataset=objects_and_rooms task_name=${cell}_objects dataset.datasets.rooms.variants.easy.frame_gap=20 seed=$seed"
          echo "$OUT/objects_then_rooms/${cell}_s$seed experiment=$cell protocol=airplane dataset=objects_and_rooms task_name=${cell}_objects curriculum.stages.full.epochs=4 curriculum.stages.full.variant=rooms_only seed=$seed"
          echo "$OUT/objects_then_far_rooms/${cell}_s$seed experiment=$cell protocol=airplane dataset=objects_and_rooms task_name=${cell}_objects curriculum.stages.full.epochs=2 curriculum.stages.full.variant=far_rooms seed=$seed" ;;
        real_choice)
          [[ $cell == rpm_gt ]] && continue
          echo "$OUT/real_choice/${cell}_test_gap_s$seed experiment=$cell protocol=real curriculum.stages.easy.variant=null seed=$seed" ;;
        dcp_choice)
          [[ ${cell##*_} == cd || ${cell##*_} == ours ]] || continue
          echo "$OUT/dcp_choice/dcp_${cell##*_}_easy_only_s$seed experiment=dcp_${cell##*_} protocol=airplane curriculum=cpu_airplane seed=$seed" ;;
        human_stretch)
          [[ $cell == rpm_gt ]] && continue
          echo "$OUT/human_stretch/${cell}_stretch0.2_s$seed experiment=$cell protocol=human +dataset.splits.train.protocol.anisotropic_scale=0.2 seed=$seed" ;;
        human_choice)
          [[ $cell == rpm_ours ]] || continue
          for setting in "0.5 5000" "2.0 5000" "0.5 20000"; do
            read -r nu lines <<< "$setting"
            echo "$OUT/human_choice/rpm_ours_nu${nu}_lines${lines}_s$seed experiment=rpm_ours protocol=human loss.nu0=$nu loss.num_lines=$lines seed=$seed"
          done ;;
        *) echo "reproduce_generalization.sh: error: unknown step '$step' (unseen_body, mixed_pairs, human_choice, objects, rooms, real_choice, dcp_choice, human_stretch, seeds)" >&2; return 2 ;;
      esac
    done
  done
}

for step in $STEPS; do runs "$step" > /dev/null; done  # unknown steps fail before any run
for step in $STEPS; do
  while read -r dir args; do
    read -r -a args <<< "$args"
    if [[ $DRY != 0 ]]; then
      echo "$dir ${args[*]}"
      continue
    fi
    if [[ -f $dir/metrics.json ]]; then
      echo "done: $dir"
      continue
    fi
    mkdir -p "$(dirname "$dir")"
    [[ -d $dir/checkpoints ]] && args+=(resume=true)
    echo "run: $dir"
    "$PY" -m train "${args[@]}" trainer.threads=1 trainer.progress=false "hydra.run.dir=$dir" >> "$dir.log" 2>&1 \
      || { tail -20 "$dir.log"; exit 1; }
  done < <(runs "$step")
done
[[ $DRY != 0 ]] || "$PY" scripts/score_generalization.py --out "$OUT/scores" --runs "$OUT" --register
