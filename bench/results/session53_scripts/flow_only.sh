# session 53: a rebuilt run (session52_scripts/rebuild.sh) copied and redone from the flow with extra overrides: flow,
# BC and evaluation only (no open-loop replay, no readers reading), for BC's spread (bc_spread.sh).
# usage: bash flow_only.sh RUN_DIR NAME OVERRIDE [OVERRIDE ...]  (venv active; one core) -> /work/runs/room_s53/<run>_<NAME>
RUN=$1; NAME=$2; shift 2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/room_s53/${B}_$NAME
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=flow analysis.tracked=false \
  analysis.open_loop=false "$V" "$@" > $W.log 2>&1
