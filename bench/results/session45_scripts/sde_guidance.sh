# session 45: SDEdit edits under strong guidance. Session 44 read each lever alone on the top block (guidance lifts
# its samples' mean; light edits keep the best condition's level): does an edit guided at 4-8 beat its condition?
# No training: --steps equals the run's 4,500, so the bench evaluates the run's own diffuser once per setting.
# usage: bash sde_guidance.sh RUN_DIR   (venv active; one core)
RUN=$1; W=/work/runs/room_s45/$(basename "$RUN")_sdeg
export OMP_NUM_THREADS=1
A="--run-dir $RUN --steps 4500 --per-block 16 --top-block --horizon 500 --streak 25 --work-dir $W"
for setting in "sde03-g4:--strength 0.3 --guidance 4" "sde05-g4:--strength 0.5 --guidance 4" \
               "sde07-g4:--strength 0.7 --guidance 4" "sde03-g8:--strength 0.3 --guidance 8" \
               "sde05-g8:--strength 0.5 --guidance 8"; do
  tag=${setting%%:*}; opts=${setting#*:}
  python bench/diffuser_conditioning.py $A $opts --tag sdeg-$tag-s45 || exit 1
done
