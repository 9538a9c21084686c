cd /work/main
while pgrep -f "results-dir bench/results/table2_s37_steps6000 " >/dev/null; do sleep 15; done
while pgrep -f "table2_s37_steps1500 " >/dev/null; do sleep 15; done
S=/work/runs/table2_s37/supplements/hopper-medium-replay; T=/work/runs/table2_s37_1500/supplements/hopper-medium-replay
OMP_NUM_THREADS=1 .venv/bin/python bench/supplement_readings.py --dataset hopper-medium-replay --supplements ftb6000_s2=$(ls -d $S/seed2/ftb-*)/supplement.pt ftb1500_s0=$(ls -d $T/seed0/ftb-*)/supplement.pt ftb1500_s1=$(ls -d $T/seed1/ftb-*)/supplement.pt ftb1500_s2=$(ls -d $T/seed2/ftb-*)/supplement.pt --out bench/results/table2_s37_readings/ftb6000_s2_ftb1500_s012.json
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 2 --kinds none,ftb --threads 1 --results-dir bench/results/table2_s37_steps6000_rl50k --runs-dir /work/runs/table2_s37_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000
.venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds 0,1,2 --kinds ftb --threads 1 --results-dir bench/results/table2_s37_steps1500_rl50k --runs-dir /work/runs/table2_s37_1500_rl50k --extra eval.max_steps=1000 augmentation.diffuser.steps=1500 td3bc.steps=50000 iql.steps=50000
