# session 45: the open-loop replays read again after nearest_start's fix (30d0d35: Euclidean instead of max-abs,
# which tied every row and replayed most samples from row 0). The runs themselves are unchanged; only the replay
# start of each generated sample is chosen again. usage: bash reread_open_loop.sh OUT.json RUN_DIR ...  (venv; one core)
OUT=$1; shift
export OMP_NUM_THREADS=1
python bench/open_loop.py --run-dirs "$@" --horizon 500 --out $OUT --no-progress
