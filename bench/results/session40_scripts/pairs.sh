# session 40: a fresh cpu diffuser on every fifth step, trained only on the pairs into the top blocks
# (bench/diffuser_conditioning.py --pair-weights); one core each. The uniform-pair baseline at the same stride:
# session 39's stride5 / stride5-long files (bench/results/session39_scripts/stride.sh).
R=/work/runs/readme_s36/run   # the README main command's run of session 36
X="--per-block 16 --top-block --horizon 500 --streak 25"
W=$1; TAG=$2; STEPS=${3:-15000}; EVERY=${4:-3000}; HOLD=${5:+--hold}
WEIGHTS=""; [ "$W" != uniform ] && WEIGHTS="--pair-weights $W"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 $WEIGHTS $HOLD \
  --steps $STEPS --eval-every $EVERY $X --work-dir /work/runs/pairs_s40/$TAG --tag $TAG-s40
# usage: bash pairs.sh W TAG [STEPS] [EVERY] [hold]; W = uniform or e.g. 0,0,1,1; "hold": --hold (trajectories held
# at their last step). Run: pairs.sh 0,0,1,1 top2; pairs.sh 0,0,0,1 top1 (stopped after 3,000 steps);
# pairs.sh uniform hold 15000 3000 hold
