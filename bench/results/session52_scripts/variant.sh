# session 52: a rebuilt run (rebuild.sh) copied and redone from the flow with extra overrides (flow, BC, evaluation,
# open-loop replay; analysis.tracked off), then session 49's readers reading (shooting, 4 candidates, each generated
# path read 4 times) into bench/results/readers_s52/<run>_<NAME>.json.
# usage: bash variant.sh RUN_DIR NAME OVERRIDE [OVERRIDE ...]  (venv active; one core) -> /work/runs/room_s52/<run>_<NAME>
# (session 53: OUT=<runs dir> and READ=<readers dir> in the environment put them elsewhere; READ=none skips the reading)
RUN=$1; NAME=$2; shift 2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
OUT=${OUT:-/work/runs/room_s52}; READ=${READ:-bench/results/readers_s52}
W=$OUT/${B}_$NAME
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=flow analysis.tracked=false \
  "$V" "$@" > $W.log 2>&1 || exit 1
[ "$READ" = none ] || bash "$(dirname "$0")/../session49_scripts/readers.sh" $W ${B}_$NAME $READ
