# session 38: SYNTHETIC seed 2 at 50k RL steps, the two methods in parallel once lanes A/B's cells are done
cd /work/main
while pgrep -f "kinds synthetic" >/dev/null; do sleep 20; done
R=bench/results/table2_s37_steps6000_rl50k
X="eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000"
for m in td3bc iql; do
  .venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 2 --kinds synthetic --methods $m --threads 1 --results-dir $R --runs-dir /work/runs/table2_s37_rl50k --extra $X &
done
wait
