#!/bin/bash
# The protocols on one walker task (walker_walk unless given second) from one FB run of sweep_fbee_f_fb.toml (small preset, 20k frames).
# Equal budgets: 20,000 environment steps of fine-tuning (the small preset's), evaluations every 5,000
# with 5 mean-action episodes; online inference: its 10 episodes (10,000 steps, no labelled data).
s=$1
T=${2:-walker_walk}
cd "${RESULTS:-.}"
DVFB=dvfb
R=sweep/runs/fb_walker_s$s
export OMP_NUM_THREADS=1
for cmd in "$DVFB zeroshot $R --task $T --protocol online_inference --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task $T --protocol latent_search --finetune.frames 20000 --finetune.eval-every 5000 --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task $T --protocol latent_search --finetune.method rela --name $T.rela --finetune.frames 20000 --finetune.eval-every 5000 --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task $T --no-progress"; do
  /usr/bin/time -f "%e s  $cmd" $cmd >> protocols_fb_${T}_s$s.log 2>&1 || echo "FAILED $cmd" >> protocols_fb_${T}_s$s.log
done
echo ALLDONE >> protocols_fb_${T}_s$s.log
