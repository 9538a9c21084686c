# session 51: after inpaint_relabel.sh on RUN: the readers reading of its flow (readers_s51/<run>_sg<L>_inpaint.json;
# relabelling touches BC only), then BC again on the samples' own actions (bc.relabel_actions=false) in a copy.
# usage: bash inpaint_followup.sh RUN_DIR LAMBDA   (venv active; one core)
RUN=$1; L=$2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/sg_s51/${B}_sg${L}_inpaint_relabel
bash "$(dirname "$0")/../session49_scripts/readers.sh" $W ${B}_sg${L}_inpaint bench/results/readers_s51
O=/work/runs/sg_s51/${B}_sg${L}_inpaint_own
rm -rf $O && cp -r $W $O
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$O resume=true redo_from=bc analysis.tracked=false \
  diffuser.score_guidance=$L diffuser.inpaint_start=true bc.relabel_actions=false "$V" > $O.log 2>&1
