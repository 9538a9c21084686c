# session 49: session 47's shooting reading (bench/tracked_replay.py, 4 candidates, greedy) of a sweep-into run,
# with every generated path read 4 times, each with other perturbations (--readers 4): each path's mean tracked
# return and success rate over the readings, a property of the path rather than of one reading's draws (session 48:
# one reading's sweep-into success is a lottery). Reading 0 is session 47's reading.
# usage: bash readers.sh RUN_DIR NAME [OUT_DIR]   (venv active; one core) -> OUT_DIR/NAME.json
# OUT_DIR defaults to bench/results/readers_s49 (session 50 reads drawer-open and more sweep-into runs into readers_s50)
OUT_DIR=${3:-bench/results/readers_s49}
mkdir -p $OUT_DIR
export OMP_NUM_THREADS=1
python bench/tracked_replay.py --run-dirs $1 --horizon 500 --candidates 4 --readers 4 \
  --out $OUT_DIR/$2.json --no-progress
