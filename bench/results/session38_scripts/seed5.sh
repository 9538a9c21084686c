# session 38: a sixth seed of the 50k-RL-step Table 2 (none and FTB-6000 in parallel), after synth2.sh
cd /work/main
while pgrep -f "synth2.sh" >/dev/null; do sleep 20; done
R=bench/results/table2_s37_steps6000_rl50k
X="eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000"
for k in none ftb; do
  .venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 5 --kinds $k --threads 1 --results-dir $R --runs-dir /work/runs/table2_s37_rl50k --extra $X &
done
wait
