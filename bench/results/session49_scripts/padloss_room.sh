# session 49: session 45's tracked room cell (v_room_tracked.sh: README configuration on data with room, v prediction,
# STEPS diffuser steps, analysis.tracked=true) with the diffusion loss also supervising the data channels on padded
# target steps (diffuser.overrides padding_loss:true). By default only the validity channel is supervised there, so the
# denoiser's data output on a generated trajectory's padding is free while sampling runs it and the convolutions carry
# it into the last valid steps; drawer-open's top block (fast successes) is mostly padding. Then what the diffuser makes
# of each block's conditions, the top block too (session 43's cond.sh at the run's own steps; no further training).
# usage: bash padloss_room.sh TASK NOISE SEED STEPS   (venv active; one core) -> /work/runs/room_s49/...
T=$1; N=$2; S=$3; P=$4
. "$(dirname "$0")/../session43_scripts/common.sh"
R=/work/runs/room_s49; mkdir -p $R; W=$R/${T}_e${N}_s${S}_v${P}_pl_tracked
python recipes/ftb_offline.py $C diffuser.steps=$P run_dir=$W analysis.tracked=true tracker.candidates=1 \
  "diffuser.overrides={prediction_type:v_prediction,padding_loss:true}" > $W.log 2>&1 || exit 1
python bench/diffuser_conditioning.py --run-dir $W --per-block 16 --top-block --horizon 500 --streak 25 \
  --tag room-pl${P}-s49 --steps $P --work-dir ${W}_own$P > ${W}_cond.log 2>&1
