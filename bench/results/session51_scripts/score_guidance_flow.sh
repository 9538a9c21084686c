# session 51: a finished v run on data with room (session 43/45's v_room*.sh) redone from the flow with score
# guidance (diffuser.score_guidance=LAMBDA: each sampler step also climbs s_psi's gradient): same diffuser, s_psi,
# blocks and top-k; flow, BC, evaluation and open-loop replay again (analysis.tracked off: the readers reading
# below replaces it). Then session 49's readers reading (shooting, 4 candidates, each generated path read 4 times)
# into bench/results/readers_s51/<run>_sg<LAMBDA>.json.
# usage: bash score_guidance_flow.sh RUN_DIR LAMBDA   (venv active; one core) -> /work/runs/sg_s51/<run>_sg<LAMBDA>
RUN=$1; L=$2
B=$(basename "$RUN"); T=$(echo $B | cut -d_ -f1); N=$(echo $B | cut -d_ -f2 | tr -d e); S=$(echo $B | cut -d_ -f3 | tr -d s)
P=$(echo $B | cut -d_ -f4 | tr -d v)
. "$(dirname "$0")/../session43_scripts/common.sh"
W=/work/runs/sg_s51/${B}_sg$L
mkdir -p /work/runs/sg_s51 && rm -rf $W && cp -r $RUN $W
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W resume=true redo_from=flow analysis.tracked=false \
  diffuser.score_guidance=$L "$V" > $W.log 2>&1 || exit 1
bash "$(dirname "$0")/../session49_scripts/readers.sh" $W ${B}_sg$L bench/results/readers_s51
