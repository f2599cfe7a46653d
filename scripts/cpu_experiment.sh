#!/usr/bin/env bash
# The CPU-scale experiment of docs/results/cpu_experiment.md: DVFB vs FB, small preset, seed 0,
# pre-trained on point_mass_maze and walker, zero-shot on every task of each domain, plus a
# uniform-random policy. Runs one job at a time (the machine has 2 cores).
#   usage: [AGENTS="dvfb fb"] [DOMAINS="point_mass_maze walker"] [FINETUNE_TASKS="walker_walk"] \
#          scripts/cpu_experiment.sh [FRAMES] [OUT_DIR]
# Re-running with a larger FRAMES resumes each run from its last checkpoint and extends it.
# The baselines' rows (docs/results/baselines.md) are the same protocol with
#   AGENTS="rnd disagreement icm_apt proto" DOMAINS=walker scripts/cpu_experiment.sh 30000 runs/baselines
# and the Meta-World rows (docs/results/metaworld.md, needs the extra: pip install -e '.[metaworld]')
#   DOMAINS=metaworld FINETUNE_TASKS="metaworld_faucet_open metaworld_faucet_close" \
#     scripts/cpu_experiment.sh 30000 runs/metaworld
set -euo pipefail
FRAMES=${1:-30000}
OUT=${2:-runs/cpu_experiment}
DVFB=${DVFB:-dvfb}
# One torch thread: the small preset is overhead-bound, and one thread degrades gracefully when
# the machine is shared (two OpenMP threads on two busy cores do not).
THREADS=${THREADS:-1}
mkdir -p "$OUT"
AGENTS=${AGENTS:-dvfb fb}
DOMAINS=${DOMAINS:-point_mass_maze walker}
for domain in $DOMAINS; do
  "$DVFB" random-policy --domain "$domain" --episodes 10 --output "$OUT/random_${domain}.json" --overwrite
  for agent in $AGENTS; do
    run="$OUT/${agent}_${domain}_s0"
    done_frames=0
    if [ -f "$run/pretrain_summary.json" ]; then
      done_frames=$(python -c "import json,sys; print(json.load(open(sys.argv[1]))['frames'])" "$run/pretrain_summary.json")
    fi
    if [ "$done_frames" -ge "$FRAMES" ]; then
      echo "== $run already pre-trained for $done_frames frames"
    elif [ -f "$run/checkpoints/latest" ]; then
      # Continue an interrupted run, or extend a finished one to FRAMES.
      "$DVFB" pretrain --agent "$agent" --domain "$domain" --preset small --frames "$FRAMES" --seed 0 \
        --run-dir "$run" --no-progress --torch-threads "$THREADS" --resume
    else
      "$DVFB" pretrain --agent "$agent" --domain "$domain" --preset small --frames "$FRAMES" --seed 0 \
        --run-dir "$run" --no-progress --torch-threads "$THREADS" --overwrite
    fi
    "$DVFB" zeroshot "$run" --task all --overwrite
  done
done

# Fine-tuning of every agent on each of FINETUNE_TASKS by its family's protocol, with the small
# preset's fine-tuning defaults (20k frames, an evaluation of 5 episodes every 5k frames). By default
# walker_walk when walker is pre-trained; each task must belong to one of DOMAINS.
if [ -z "${FINETUNE_TASKS+set}" ]; then
  FINETUNE_TASKS=""
  if [[ " $DOMAINS " == *" walker "* ]]; then FINETUNE_TASKS="walker_walk"; fi
fi
if [ "${FINETUNE:-1}" = 1 ]; then
  for task in $FINETUNE_TASKS; do
    domain=$(python -c "import sys, dvfb.envs as e; print(e.TASKS[sys.argv[1]].domain)" "$task")
    for agent in $AGENTS; do
      run="$OUT/${agent}_${domain}_s0"
      if [ ! -f "$run/finetune/$task/finetune_summary.json" ]; then
        "$DVFB" finetune "$run" --task "$task" --no-progress --overwrite
      fi
    done
  done
fi
