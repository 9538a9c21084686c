cd /work/main
R=bench/results/table2_s37_steps6000_rl50k
X="eval.max_steps=1000 augmentation.diffuser.steps=6000 td3bc.steps=50000 iql.steps=50000"
for spec in "none 4" "ftb 4" "synthetic 1"; do set -- $spec
  .venv/bin/python bench/table2.py --tasks hopper-medium-replay --seeds $2 --kinds $1 --threads 1 --results-dir $R --runs-dir /work/runs/table2_s37_rl50k --extra $X
done
