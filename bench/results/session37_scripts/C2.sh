cd /work/main
while pgrep -f "sh /work/scratch/s37/C.sh" >/dev/null; do sleep 15; done
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 3,4 --kinds none,ftb --threads 1 --results-dir bench/results/table2_s37_steps6000 --runs-dir /work/runs/table2_s37 --extra eval.max_steps=1000 augmentation.diffuser.steps=6000 augmentation.tracked=true
