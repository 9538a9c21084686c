# session 51: a score-guided run (score_guidance_flow.sh) with BC redone on actions the inverse-dynamics tracker gives
# for the final set's own states (bc.relabel_actions=true; the guided samples' own actions give BC 0 success on
# button-press seed 4), then the evaluation again.
# usage: bash relabel_bc.sh GUIDED_RUN_DIR   (venv active; one core) -> GUIDED_RUN_DIR_relabel
RUN=$1
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v); L=${B##*_sg}
. "$(dirname "$0")/../session43_scripts/common.sh"
W=${RUN}_relabel
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=bc analysis.tracked=false \
  diffuser.score_guidance=$L bc.relabel_actions=true "$V" > $W.log 2>&1
