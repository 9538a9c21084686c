# session 44: the v run of session 43's v_room.sh (same data, labels, s_psi and blocks) with its diffuser retrained
# on the top block's own pairs too (diffuser.top_block_pairs=true), then the flow, BC and evaluation.
# usage: bash top_pairs.sh TASK NOISE SEED STEPS  -> /work/runs/room_s44/TASK_e<NOISE>_s<SEED>_tp<STEPS>
# (needs /work/runs/room_s43/TASK_e<NOISE>_s<SEED>_v<STEPS> done; venv active; one core)
T=$1; N=$2; S=$3; P=$4
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/room_s44/${T}_e${N}_s${S}_tp$P
mkdir -p /work/runs/room_s44 && rm -rf $W && cp -r $R/${T}_e${N}_s${S}_v$P $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=diffuser \
  diffuser.top_block_pairs=true "$V" > $W.log 2>&1
