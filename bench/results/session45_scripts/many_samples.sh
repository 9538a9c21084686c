# session 45: does the v diffuser put any mass above the data's best at all? 128 samples per block (the sweeps drew
# 16) at the guidance that lifted each task's top block most (session 44), read off the samples' states: the top
# block's max against its conditions'. No training. usage: bash many_samples.sh RUN_DIR GUIDANCE  (venv; one core)
RUN=$1; G=$2; W=/work/runs/room_s45/$(basename "$RUN")_many
export OMP_NUM_THREADS=1
python bench/diffuser_conditioning.py --run-dir $RUN --steps 4500 --per-block 128 --top-block --horizon 500 \
  --streak 25 --work-dir $W --guidance $G --tag many-g$G-s45
