cd /work/main
S=/work/runs/table2_s37/supplements/hopper-medium-replay
while pgrep -f "sh /work/scratch/s37/C2.sh" >/dev/null; do sleep 15; done
OMP_NUM_THREADS=1 .venv/bin/python bench/supplement_readings.py --dataset hopper-medium-replay --supplements synthetic6000_s0=$(ls -d $S/seed0/synthetic-*)/supplement.pt --out bench/results/table2_s37_readings/synthetic6000_s0.json
while pgrep -f "kinds synthetic" >/dev/null; do sleep 15; done
OMP_NUM_THREADS=1 .venv/bin/python bench/supplement_readings.py --dataset hopper-medium-replay --supplements synthetic6000_s1=$(ls -d $S/seed1/synthetic-*)/supplement.pt synthetic6000_s2=$(ls -d $S/seed2/synthetic-*)/supplement.pt --out bench/results/table2_s37_readings/synthetic6000_s12.json
