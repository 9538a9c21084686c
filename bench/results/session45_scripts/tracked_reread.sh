# session 45: closed-loop tracked replays (bench/tracked_replay.py) of runs after nearest_start's fix (30d0d35):
# does a guidance-4/8 flow's final set, its state paths executed by the inverse-dynamics tracker from the right
# episode's start, beat the top-k? usage: bash tracked_reread.sh OUT.json RUN_DIR ...   (venv active; one core)
OUT=$1; shift
export OMP_NUM_THREADS=1
python bench/tracked_replay.py --run-dirs "$@" --horizon 500 --candidates 1 --out $OUT --no-progress
