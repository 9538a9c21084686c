# session 44: the conditioning bench on a top-block-pairs run's own diffuser (4,500 steps, no training), at the
# paper's guidance 1.2 and at 4.   usage: bash tp_cond.sh RUN_DIR   (venv active; one core)
RUN=$1; W=/work/runs/room_s44/$(basename "$RUN")_cond
export OMP_NUM_THREADS=1
A="--run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 --streak 25 --work-dir $W"
for g in 1.2 4; do python bench/diffuser_conditioning.py $A --guidance $g --tag tp-g$g-s44 || exit 1; done
