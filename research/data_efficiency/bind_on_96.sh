#!/usr/bin/env bash
# Session 60: does a fresh grounding bind on 96 episodes, from the shipped model's System 1?
# (a) 96 clean episodes (8 a task); (b) step 30's 96 (3 clean + 5 after a prelude a task).
set -euxo pipefail
cd "$(dirname "$0")/../.."
. .venv/bin/activate
date
trivla-drake collect --out data/bind-clean96 --episodes-per-task 8 --workers 2 --no-progress
date
trivla-drake collect --out data/bind-mix96 --episodes-per-task 3 --workers 2 --no-progress
trivla-drake collect --out data/bind-mix96 --episodes-per-task 8 --prelude-tasks 4 --workers 2 --no-progress
date
BIND=(train --stage policy --feature-stride 3 --vl-position-embedding --grounding-weight 1 --threads 2
      --init models/trivla_cpu --grounding-phase bind --lr 2e-3 --warmup-steps 1 --min-lr-ratio 1 --beta2 0.999
      --grad-clip 0 --steps 1200 --batch-size 64 --subgoal-offset)
for name in clean96 mix96; do
  trivla-drake "${BIND[@]}" --data data/bind-$name --out runs/shippedbind_$name
  date
  trivla-drake probe --checkpoint runs/shippedbind_$name/final --grounding-scenes 10 --threads 2 > results/data_efficiency/grounding_check_shippedbind_$name.md.part
  mv results/data_efficiency/grounding_check_shippedbind_$name.md.part results/data_efficiency/grounding_check_shippedbind_$name.md
  date
done
