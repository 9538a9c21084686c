# session 47: the tracked reading with shooting in the simulator (bench/tracked_replay.py --candidates 4: each step
# the path's own action, the inverse-dynamics tracker's and two perturbations, the one landing nearest the path's
# next hand, gripper and object kept; exact on recorded paths). Sweep-into's tracker alone reproduced its top-k
# poorly (recorded mean 342, tracked 168; sessions 31-46). One results file per run, written as each finishes.
# usage: bash shoot_reread.sh OUT_DIR RUN_DIR ...   (venv active; one core)
OUT=$1; shift
export OMP_NUM_THREADS=1
mkdir -p $OUT
for RUN in "$@"; do
  python bench/tracked_replay.py --run-dirs $RUN --horizon 500 --candidates 4 --readers 1 --out $OUT/$(basename $RUN).json \
    --no-progress || exit 1
done
