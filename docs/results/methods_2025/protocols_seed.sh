#!/bin/bash
# The protocols from one walker run of a sweep (small preset, 20k frames):
#   protocols_seed.sh SEED [AGENT [TASK [rela]]]     (defaults: dvfb, walker_walk; ReLA only when asked)
# Equal budgets: 20,000 environment steps of fine-tuning (the small preset's), evaluations every 5,000
# with 5 mean-action episodes; online inference: its 10 episodes (10,000 steps, no labelled data).
s=$1
A=${2:-dvfb}
T=${3:-walker_walk}
cd "${RESULTS:-.}"
DVFB=dvfb
R=sweep/runs/${A}_walker_s$s
LOG=protocols_${A}_${T}_s$s.log
SEARCH="--protocol latent_search --finetune.frames 20000 --finetune.eval-every 5000 --finetune.eval-episodes 5"
export OMP_NUM_THREADS=1
commands=("$DVFB zeroshot $R --task $T --protocol online_inference --finetune.eval-episodes 5 --no-progress"
          "$DVFB finetune $R --task $T $SEARCH --no-progress")
if [ "${4:-}" = rela ]; then
  commands+=("$DVFB finetune $R --task $T $SEARCH --finetune.method rela --name $T.rela --no-progress")
fi
commands+=("$DVFB finetune $R --task $T --no-progress")
for cmd in "${commands[@]}"; do
  /usr/bin/time -f "%e s  $cmd" $cmd >> $LOG 2>&1 || echo "FAILED $cmd" >> $LOG
done
echo ALLDONE >> $LOG
