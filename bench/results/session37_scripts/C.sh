cd /work/main
while pgrep -f "table2_s37_steps1500 " >/dev/null; do sleep 15; done
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 0,1 --kinds none,ftb --threads 1 --results-dir bench/results/table2_s37_steps6000_rl50k --runs-dir /work/runs/table2_s37_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000
