# session 45: session 43's v run (v_room.sh's first half: README configuration on data with room, v prediction,
# STEPS diffuser steps) with the recipe's closed-loop tracked reading (analysis.tracked=true) of top-k and final set,
# after nearest_start's fix. usage: bash v_room_tracked.sh TASK NOISE SEED STEPS  -> /work/runs/room_s45/...
T=$1; N=$2; S=$3; P=$4
. "$(dirname "$0")/../session43_scripts/common.sh"
R=/work/runs/room_s45; mkdir -p $R; W=$R/${T}_e${N}_s${S}_v${P}_tracked
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W analysis.tracked=true tracker.candidates=1 "$V" > $W.log 2>&1
