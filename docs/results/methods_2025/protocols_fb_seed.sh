#!/bin/bash
# The protocols on walker_walk from one FB run of sweep_fbee_f_fb.toml (small preset, 20k frames).
# Equal budgets: 20,000 environment steps of fine-tuning (the small preset's), evaluations every 5,000
# with 5 mean-action episodes; online inference: its 10 episodes (10,000 steps, no labelled data).
s=$1
cd "${RESULTS:-.}"
DVFB=dvfb
R=sweep/runs/fb_walker_s$s
export OMP_NUM_THREADS=1
for cmd in "$DVFB zeroshot $R --task walker_walk --protocol online_inference --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task walker_walk --protocol latent_search --finetune.frames 20000 --finetune.eval-every 5000 --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task walker_walk --protocol latent_search --finetune.method rela --name walker_walk.rela --finetune.frames 20000 --finetune.eval-every 5000 --finetune.eval-episodes 5 --no-progress" \
           "$DVFB finetune $R --task walker_walk --no-progress"; do
  /usr/bin/time -f "%e s  $cmd" $cmd >> protocols_fb_s$s.log 2>&1 || echo "FAILED $cmd" >> protocols_fb_s$s.log
done
echo ALLDONE >> protocols_fb_s$s.log
