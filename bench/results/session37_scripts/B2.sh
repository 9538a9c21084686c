cd /work/main
while pgrep -f supplement_readings.py >/dev/null; do sleep 10; done
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 0,1,2 --kinds ftb --threads 1 --results-dir bench/results/table2_s37_steps1500 --runs-dir /work/runs/table2_s37_1500 --extra eval.max_steps=1000 augmentation.diffuser.steps=1500
