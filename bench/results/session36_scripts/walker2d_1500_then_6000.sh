#!/bin/bash
# Session 36: walker2d-medium-replay seed 0 at the cpu preset's 1,500 diffuser steps, then the same run extended to
# 6,000 steps with the recipe's resume=true diffuser.steps=6000 (trains on from step 1,500, redoes flow and later).
set -e
cd /work/main
EXTRA="labels.num_pairs=15 blocks.num_blocks=10 flow.top_k=50 flow.threshold=1.05 bc.weight_decay=2e-4 eval.max_steps=1000 analysis.tracked=true"
.venv/bin/python bench/table1.py --methods ftb --tasks walker2d-medium-replay --teacher return --seeds 0 --threads 1 \
  --results-dir bench/results/table1_v2_locomotion_s36_walker2d_steps1500 --runs-dir /work/runs/walker_s36/r1500 \
  --extra $EXTRA diffuser.steps=1500
SRC=/work/runs/walker_s36/r1500/walker2d-medium-replay/return/ftb/seed0
DST=/work/runs/walker_s36/r6000/seed0
mkdir -p $(dirname $DST); rm -rf $DST; cp -a $SRC $DST
OMP_NUM_THREADS=1 .venv/bin/python recipes/ftb_offline.py env.name=walker2d +dataset.options.kind=medium-replay seed=0 labels.teacher=return \
  preset=cpu run_dir=$DST resume=true progress=false $EXTRA diffuser.steps=6000
.venv/bin/python bench/table1.py --import-run $DST --results-dir bench/results/table1_v2_locomotion_s36_walker2d_steps6000
