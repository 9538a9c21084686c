# session 45: guidance 4 collapsed sweep-into's policy (0.70 -> 0.06; the final set is 90 % generated). Does BC on
# the tracker's actions for the samples' own states (bc.relabel_actions=true) bring it back? A copy of the
# guidance-4 run redone from BC. usage: bash relabel_g4.sh RUN_DIR  -> RUN_DIR_relabel   (venv active; one core)
RUN=$1
T=$(basename "$RUN" | cut -d_ -f1); N=$(basename "$RUN" | cut -d_ -f2 | tr -d e); S=$(basename "$RUN" | cut -d_ -f3 | tr -d s)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=${RUN}_relabel
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=4500 run_dir=$W resume=true redo_from=bc bc.relabel_actions=true \
  diffuser.guidance=4 "$V" > $W.log 2>&1
