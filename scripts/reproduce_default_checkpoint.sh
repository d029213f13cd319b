#!/usr/bin/env bash
# Rebuilds models/trivla_cpu and the tables in results/ exactly as they were made (2 CPU cores, about
# 3 hours; every step resumes or reuses its caches if rerun). Run from the repository root in the
# project's virtualenv. DATA and RUNS may be moved elsewhere.
set -euo pipefail
DATA=${DATA:-data/sim}
RUNS=${RUNS:-runs}
export OMP_WAIT_POLICY=PASSIVE

# 1. 20 oracle demonstrations per task (240 episodes), then System 3 on their clips (eq. 1).
trivla-drake collect --out "$DATA" --episodes-per-task 20
trivla-drake train --stage video --data "$DATA" --out "$RUNS/video" --preset cpu --steps 1200 --threads 2
# 2. 10 more per task (seeds continue where the first run stopped): 360 episodes.
trivla-drake collect --out "$DATA" --episodes-per-task 30
# 3. System 2 on simulator-generated visual questions.
trivla-drake train --stage vlm --out "$RUNS/vlm" --init "$RUNS/video/final" --steps 1000 --threads 2
# 4. System 1 by flow matching (eq. 5) on cached System 2/3 features (standardised with statistics
#    of the training episodes), and the ablation / data arms (same steps and batch; Systems 2 and 3
#    are untouched by the policy stage).
#    The shipped checkpoint predates System 1's tcp features (now on by default): --no-tcp-features.
POLICY=(train --stage policy --data "$DATA" --steps 3000 --feature-stride 3 --no-tcp-features)
trivla-drake "${POLICY[@]}" --out "$RUNS/policy" --init "$RUNS/vlm/final" --threads 2
trivla-drake "${POLICY[@]}" --out "$RUNS/policy_s13" --init "$RUNS/video/final" --no-system2 --threads 1
trivla-drake "${POLICY[@]}" --out "$RUNS/policy_s1" --init "$RUNS/video/final" --no-system2 --no-system3 --threads 1
trivla-drake "${POLICY[@]}" --out "$RUNS/policy_data10" --init "$RUNS/vlm/final" --fraction 0.1 --threads 1
# 5. The shipped checkpoint (float16 weights) and the tables.
trivla-drake export "$RUNS/policy/final" --out models/trivla_cpu
trivla-drake tables --full models/trivla_cpu --system1-3 "$RUNS/policy_s13/final" \
    --system1 "$RUNS/policy_s1/final" --data10 "$RUNS/policy_data10/final" \
    --episodes 2 --chains 3 --workers 2 --latency-tasks rotate_block_left,turn_off_light,unstack_block \
    --out results
# 6. How well the frozen features locate the blocks (linear probes), with System 3's noise fixed / random.
trivla-drake probe --data "$DATA" --checkpoint models/trivla_cpu --threads 2 > results/feature_probe.md
trivla-drake probe --data "$DATA" --checkpoint models/trivla_cpu --threads 2 --feature-noise random \
    > results/feature_probe_random_noise.md
# 7. Optional (reported in the README, not shipped): 3000 more System 1 steps at 3x the learning rate,
#    then `trivla-drake evaluate --policy "$RUNS/policy_longer/final" --episodes 2 --chains 3 --seed S`
#    for S in 1000 1001 1002.
if [[ "${LONGER:-0}" == 1 ]]; then
  trivla-drake train --stage policy --data "$DATA" --out "$RUNS/policy_longer" --init "$RUNS/policy/final" \
      --lr 3e-4 --steps 3000 --feature-stride 3 --seed 1 --no-tcp-features --threads 2
fi
# Optional (DART=1): the experiment with recovery demonstrations and tcp features, not shipped
# (results/dart_tcp_experiment/): 30 more episodes per task with perturbation bursts, then the
# three arms on all 720 episodes with the tcp features, at 3e-4 for 3000 steps, then each arm for
# 6000 more steps (9000 in all), and the full arm 4500 more again (13500). The full arm is
# evaluated as its float16 export, like the shipped one.
if [[ "${DART:-0}" == 1 ]]; then
  DART_DATA=${DART_DATA:-$DATA-dart}
  [[ -d "$DART_DATA" ]] || cp -r "$DATA" "$DART_DATA"
  trivla-drake collect --out "$DART_DATA" --episodes-per-task 60 --action-noise 1
  DART_POLICY=(train --stage policy --data "$DART_DATA" --lr 3e-4 --feature-stride 3 --threads 1)
  trivla-drake "${DART_POLICY[@]}" --steps 3000 --out "$RUNS/dart_policy" --init "$RUNS/vlm/final"
  trivla-drake "${DART_POLICY[@]}" --steps 3000 --out "$RUNS/dart_s13" --init "$RUNS/video/final" --no-system2
  trivla-drake "${DART_POLICY[@]}" --steps 3000 --out "$RUNS/dart_s1" --init "$RUNS/video/final" --no-system2 --no-system3
  trivla-drake "${DART_POLICY[@]}" --steps 6000 --seed 1 --out "$RUNS/dart_policy_9k" --init "$RUNS/dart_policy/final"
  trivla-drake "${DART_POLICY[@]}" --steps 6000 --seed 1 --out "$RUNS/dart_s13_9k" --init "$RUNS/dart_s13/final" --no-system2
  trivla-drake "${DART_POLICY[@]}" --steps 6000 --seed 1 --out "$RUNS/dart_s1_9k" --init "$RUNS/dart_s1/final" \
      --no-system2 --no-system3
  trivla-drake "${DART_POLICY[@]}" --steps 4500 --seed 2 --out "$RUNS/dart_policy_13500" --init "$RUNS/dart_policy_9k/final"
  for run in dart_policy dart_policy_9k dart_policy_13500; do
    trivla-drake export "$RUNS/$run/final" --out "$RUNS/${run}_export"
  done
  for policy in dart_policy_export dart_s13/final dart_s1/final dart_policy_9k_export dart_s13_9k/final dart_s1_9k/final \
      dart_policy_13500_export; do
    for seed in 1000 1001 1002; do
      trivla-drake evaluate --policy "$RUNS/$policy" --episodes 2 --chains 3 --seed "$seed" --workers 2
    done
  done
fi
