# session 45: the v diffuser's top-block samples under other samplers at guidance 4. The recipe's DDPM-25 was chosen
# on an epsilon model in session 27; does a deterministic or finer sampler get nearer the conditions?
# No training (--steps equals the run's 4,500). usage: bash sampler_g4.sh RUN_DIR   (venv active; one core)
RUN=$1; W=/work/runs/room_s45/$(basename "$RUN")_samplers
export OMP_NUM_THREADS=1
A="--run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 --streak 25 --work-dir $W --guidance 4"
for setting in "ddim25:--sampler ddim --sample-steps 25" "dpmpp20:--sampler dpm++ --sample-steps 20" \
               "ddpm100:--sampler ddpm --sample-steps 100"; do
  tag=${setting%%:*}; opts=${setting#*:}
  python bench/diffuser_conditioning.py $A $opts --tag smp-$tag-g4-s45 || exit 1
done
