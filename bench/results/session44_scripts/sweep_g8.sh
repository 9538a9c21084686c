# session 44: sampler_sweep.sh's bench at guidance 8 (added after the sweep showed guidance lifting the top blocks).
# usage: bash sweep_g8.sh RUN_DIR   (venv active; one core)
RUN=$1; W=/work/runs/room_s44/$(basename "$RUN")_sweep
export OMP_NUM_THREADS=1
python bench/diffuser_conditioning.py --run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 --streak 25 \
  --work-dir $W --guidance 8 --tag sweep-g8-s44
