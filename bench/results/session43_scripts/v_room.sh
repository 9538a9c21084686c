# session 43: v prediction from the start at STEPS diffuser steps on data with room (session 42's room_seed.sh
# through common.sh), then BC on s_psi's top-k alone (a copy redone from the flow with flow.flow_steps=0).
# usage: bash v_room.sh TASK NOISE SEED STEPS  -> /work/runs/room_s43/TASK_e<NOISE>_s<SEED>_{v,topk}<STEPS>
T=$1; N=$2; S=$3; P=$4
. "$(dirname "$0")/common.sh"
W=$R/${T}_e${N}_s${S}
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=${W}_v$P "$V" > ${W}_v$P.log 2>&1 || exit 1
rm -rf ${W}_topk$P && cp -r ${W}_v$P ${W}_topk$P
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=${W}_topk$P resume=true redo_from=flow flow.flow_steps=0 \
  "$V" > ${W}_topk$P.log 2>&1 || exit 1
