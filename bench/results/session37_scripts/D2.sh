cd /work/main
while pgrep -f "supplement_readings.py" >/dev/null; do sleep 10; done
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 2 --kinds none,ftb --threads 1 --results-dir bench/results/table2_s37_steps6000_rl50k --runs-dir /work/runs/table2_s37_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 0,1,2 --kinds synthetic --threads 1 --results-dir bench/results/table2_s37_steps6000 --runs-dir /work/runs/table2_s37 --extra eval.max_steps=1000 augmentation.diffuser.steps=6000
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 0,1,2 --kinds ftb --threads 1 --results-dir bench/results/table2_s37_steps1500_rl50k --runs-dir /work/runs/table2_s37_1500_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=1500 td3bc.steps=50000 iql.steps=50000
