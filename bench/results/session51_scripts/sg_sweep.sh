# session 51: what score guidance (diffuser.score_guidance = lambda) does to one run's diffuser samples, before any
# flow: bench/diffuser_conditioning.py at the run's own 4,500 steps (no training), 16 conditions per block plus the
# top block, stop-rule returns, at lambda = 0, 0.1, 0.3 and 1.
# usage: bash sg_sweep.sh RUN_DIR [RUN_DIR ...]   (venv active; one core)
export OMP_NUM_THREADS=1
for RUN in "$@"; do
  for L in 0 0.1 0.3 1; do
    python bench/diffuser_conditioning.py --run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 \
      --streak 25 --work-dir /work/runs/sg_s51/sweep_$(basename $RUN) --score-guidance $L --tag sg$L-s51 || exit 1
  done
done
