# session 51: score_guidance_flow.sh's redo from the flow with each sample held at its condition's real start
# (diffuser.inpaint_start=true: the guide cannot move the start) and BC on relabelled actions (bc.relabel_actions=true),
# no readers reading: does BC's policy come back?  usage: bash inpaint_relabel.sh RUN_DIR LAMBDA (venv; one core)
RUN=$1; L=$2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/sg_s51/${B}_sg${L}_inpaint_relabel
rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=flow analysis.tracked=false \
  diffuser.score_guidance=$L diffuser.inpaint_start=true bc.relabel_actions=true "$V" > $W.log 2>&1
