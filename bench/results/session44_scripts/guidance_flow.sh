# session 44: a finished v run (session 43's v_room.sh, reproduced) redone from the flow with another classifier-free
# guidance weight (the paper's Table 5: 1.2): same diffuser, s_psi and top-k; flow, BC, evaluation and replays again.
# usage: bash guidance_flow.sh RUN_DIR GUIDANCE  -> /work/runs/room_s44/<run>_g<GUIDANCE>   (venv active; one core)
RUN=$1; G=$2
T=$(basename "$RUN" | cut -d_ -f1); N=$(basename "$RUN" | cut -d_ -f2 | tr -d e); S=$(basename "$RUN" | cut -d_ -f3 | tr -d s)
P=$(basename "$RUN" | sed 's/.*_[a-z]*\([0-9]*\)$/\1/')
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/room_s44/$(basename "$RUN")_g$G
mkdir -p /work/runs/room_s44 && rm -rf $W && cp -r $RUN $W
EXTRA=$(grep -q "top_block_pairs: true" $RUN/config.yaml && echo diffuser.top_block_pairs=true)  # keep its pairing
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=flow diffuser.guidance=$G \
  "$V" $EXTRA > $W.log 2>&1
