# session 53: score guidance on SDEdit edits of the condition (diffuser.strength < 1 with diffuser.score_guidance),
# never combined before: session 44 found SDEdit 0.3 keeps top-block samples by their conditions (drawer-open 3,248
# against 3,620; gap 0.07) but never above them, session 51 that score guidance lifts fresh samples' s_psi but takes
# them off the data. bench/diffuser_conditioning.py at the run's own 4,500 steps (no training), 16 conditions per block
# plus the top block, stop-rule returns.
# usage: bash sdedit_sg_sweep.sh STRENGTH "LAMBDAS" RUN_DIR [RUN_DIR ...]   (venv active; one core)
export OMP_NUM_THREADS=1
S=$1; LS=$2; shift 2
for RUN in "$@"; do
  for L in $LS; do
    python bench/diffuser_conditioning.py --run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 \
      --streak 25 --work-dir /work/runs/room_s53/sweep_$(basename $RUN) --strength $S --score-guidance $L \
      --tag sde$S-sg$L-s53 || exit 1
  done
done
