# session 39: SYNTHETIC seeds 3-5 at 50k RL steps (one lane, one core), so FTB - SYNTHETIC has six pairs
cd /work/main
R=bench/results/table2_s37_steps6000_rl50k
X="eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000"
for s in 3 4 5; do
  .venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds $s --kinds synthetic --threads 1 --results-dir $R --runs-dir /work/runs/table2_s37_rl50k --extra $X
done
