# session 52: a finished variant (variant.sh) copied and redone from BC with extra BC overrides (same flow, so no new
# readers reading); its metrics.json gives the policy.
# usage: bash redo_bc.sh VARIANT_DIR NAME "VARIANT_OVERRIDES" BC_OVERRIDE [...]  (venv active; one core)
#   -> /work/runs/room_s52/<variant>_<NAME>
RUN=$1; NAME=$2; VO=$3; shift 3
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/room_s52/${B}_$NAME
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=bc analysis.tracked=false \
  "$V" $VO "$@" > $W.log 2>&1
