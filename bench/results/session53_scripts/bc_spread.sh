# session 53: BC's own spread on one flowed set. A finished run (variant.sh / flow_only.sh) is copied once per BC seed
# and redone from BC with bc.seed=K (same flow, same evaluation seeds); each copy's metrics.json gives the policy.
# usage: bash bc_spread.sh RUN_DIR "RUN_OVERRIDES" SEED [SEED ...]  (venv active; one core)
#   -> /work/runs/room_s53/<run>_bcseed<K>[_<TAG>]; RUN_OVERRIDES: the overrides the run was made with (the flow's are
#   locked) plus any BC ones; TAG=<name> in the environment keeps such a variant's copies apart; KEEP=<dir> (session 54)
#   copies each copy's metrics.json and report.md into <dir>/<copy name>/ (the repository's bench/results/*/runs/)
RUN=$1; VO=$2; shift 2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
for K in "$@"; do
  W=/work/runs/room_s53/${B}_bcseed$K${TAG:+_$TAG}
  rm -rf $W && cp -r $RUN $W
  python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=bc analysis.tracked=false \
    "$V" $VO bc.seed=$K > $W.log 2>&1 || { echo "failed: $W"; continue; }
  python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print(sys.argv[2], m['bc']['seed'], m['eval']['success_rate'])" \
    $W/metrics.json $B
  [ -z "$KEEP" ] || { mkdir -p $KEEP/$(basename $W) && cp $W/metrics.json $W/report.md $KEEP/$(basename $W)/; }
done
