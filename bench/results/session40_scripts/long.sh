# session 40: continue a pairs.sh work dir to more steps under its own tag (TAG-long-s40), as session 39's
# stride5-long. usage: bash long.sh W TAG STEPS EVERY [hold]  (W and hold as that work dir was trained)
R=/work/runs/readme_s36/run
X="--per-block 16 --top-block --horizon 500 --streak 25"
W=$1; TAG=$2; STEPS=$3; EVERY=$4; HOLD=${5:+--hold}
WEIGHTS=""; [ "$W" != uniform ] && WEIGHTS="--pair-weights $W"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 $WEIGHTS $HOLD \
  --steps $STEPS --eval-every $EVERY $X --work-dir /work/runs/pairs_s40/$TAG --tag $TAG-long-s40
