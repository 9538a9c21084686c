# session 37, last: the third rl50k seed (both kinds in parallel, one core each)
cd /work/main
for k in none ftb; do
  .venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 1 --kinds $k --threads 1 --results-dir bench/results/table2_s37_steps6000_rl50k --runs-dir /work/runs/table2_s37_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000 &
done
wait
