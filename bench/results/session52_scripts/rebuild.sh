# session 52: rebuild a session-45 v run (v_room_tracked.sh's configuration: README configuration on data with room,
# v prediction, STEPS diffuser steps) up to the diffuser on a fresh machine (the session-45 runs did not carry over);
# the flow variants are redone from the flow (variant.sh). Same seeds and code path, so the dataset, labels, s_psi,
# blocks and top-k are the ones sessions 45-51 read. (Session 54: a finished rebuild is left alone and a partial one
# resumed, as session 53's check_seed.sh and session 54's ens_seed.sh need.)
# usage: bash rebuild.sh TASK NOISE SEED STEPS  (venv active; one core) -> /work/runs/room_s52/TASK_e<N>_s<S>_v<STEPS>
T=$1; N=$2; S=$3; P=$4
. "$(dirname "$0")/../session43_scripts/common.sh"
R=/work/runs/room_s52; mkdir -p $R; W=$R/${T}_e${N}_s${S}_v${P}
grep -q '"diffuser"' $W/stages.json 2>/dev/null && exit 0
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W stop_after=diffuser resume=true "$V" >> $W.log 2>&1
