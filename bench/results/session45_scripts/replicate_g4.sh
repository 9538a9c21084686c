# session 45: does guidance 4's rise of the executed max (session 44, sweep-into seed 6 only) repeat on other seeds?
# For each TASK:NOISE:SEED: session 43's v run rebuilt (v_room.sh), then redone from the flow at guidance 4
# (guidance_flow.sh). usage: bash replicate_g4.sh TASK:NOISE:SEED ...   (venv active; one core)
D=$(dirname "$0")/..
for cell in "$@"; do
  IFS=: read -r T N S <<< "$cell"
  bash $D/session43_scripts/v_room.sh $T $N $S 4500 || exit 1
  bash $D/session44_scripts/guidance_flow.sh /work/runs/room_s43/${T}_e${N}_s${S}_v4500 4 || exit 1
done
