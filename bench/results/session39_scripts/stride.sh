# session 39: the cpu diffuser on every fifth step (bench/diffuser_conditioning.py --stride), one core
R=/work/runs/readme_s36/run   # the README main command's run of session 36
X="--per-block 16 --top-block --horizon 500 --streak 25"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --steps 1500 $X --work-dir /work/runs/stride_s39/own1500 --tag own1500-s39
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 --steps 15000 --eval-every 3000 $X --work-dir /work/runs/stride_s39/s5 --tag stride5-s39
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 --steps 45000 --eval-every 10000 $X --work-dir /work/runs/stride_s39/s5 --tag stride5-long-s39
OMP_NUM_THREADS=1 python bench/coarsen_round_trip.py --run-dir $R --strides 2 5 10 --horizon 500 --streak 25 --out bench/results/coarsen_round_trip/button-press-v3-readme_s36-s39.json
