# session 46: session 45's v_room_tracked.sh (README configuration on data with room, v prediction, 4,500 diffuser
# steps, the recipe's closed-loop tracked reading) run over a queue of TASK:NOISE:SEED cells, one after another on one
# core. Does drawer-open seed 4's tracked max rise repeat on other seeds and on button-press?
# usage: bash tracked_queue.sh TASK:NOISE:SEED ...   (venv active)  -> /work/runs/room_s45/..._tracked
D=$(dirname "$0")/..
for cell in "$@"; do
  IFS=: read -r T N S <<< "$cell"
  bash $D/session45_scripts/v_room_tracked.sh $T $N $S 4500 || exit 1
done
