# session 44: how the flow's sampler options move the top block's samples of one v diffuser (no training:
# --steps equals the run's 4,500, so the bench evaluates the run's own diffuser once per setting).
# usage: bash sampler_sweep.sh RUN_DIR   (venv active; one core)
RUN=$1; W=/work/runs/room_s44/$(basename "$RUN")_sweep
export OMP_NUM_THREADS=1
A="--run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 --streak 25 --work-dir $W"
for setting in "g1.2:--guidance 1.2" "g2:--guidance 2" "g4:--guidance 4" "sde05:--strength 0.5" \
               "sde03:--strength 0.3" "inpaint:--inpaint-start" "inpaint-g2:--inpaint-start --guidance 2"; do
  tag=${setting%%:*}; opts=${setting#*:}
  python bench/diffuser_conditioning.py $A $opts --tag sweep-$tag-s44 || exit 1
done
