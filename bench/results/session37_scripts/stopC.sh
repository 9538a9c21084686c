# stop C when its seed-1 cells start (seed 0 done): kill the table2.py of C and its recipe child
while ! grep -q "seed1.json" /work/scratch/s37/t2_C.log; do sleep 10; done
P=$(pgrep -f "results-dir bench/results/table2_s37_steps6000_rl50k --runs-dir /work/runs/table2_s37_rl50k" | head -n 20)
for p in $(pgrep -f "seeds 0,1 --kinds none,ftb --threads 1 --results-dir bench/results/table2_s37_steps6000_rl50k"); do pkill -P $p; kill $p; done
pkill -f "run_dir=/work/runs/table2_s37_rl50k/none/hopper-medium-replay/return/td3bc/seed1"
echo stopped C at $(date)
