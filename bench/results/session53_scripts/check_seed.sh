# session 53: does flow.max_hand_penetration=0 cost the paper's flow (lambda = 0) its BC policy? One rebuilt run
# (session52_scripts/rebuild.sh; a killed or partial rebuild is resumed), the flow without and with the check
# (flow_only.sh), then BC seeds 0-3 on each (bc_spread.sh).
# usage: bash check_seed.sh TASK NOISE SEED   (venv active; one core)
T=$1; N=$2; S=$3
D=$(dirname "$0"); W=/work/runs/room_s52/${T}_e${N}_s${S}_v4500
bash $D/../session52_scripts/rebuild.sh $T $N $S 4500 || exit 1
bash $D/flow_only.sh $W sg0 diffuser.score_guidance=0 || exit 1
bash $D/flow_only.sh $W sg0_pen0 diffuser.score_guidance=0 flow.max_hand_penetration=0 || exit 1
B=/work/runs/room_s53/$(basename $W)
bash $D/bc_spread.sh ${B}_sg0 "diffuser.score_guidance=0" 0 1 2 3
bash $D/bc_spread.sh ${B}_sg0_pen0 "diffuser.score_guidance=0 flow.max_hand_penetration=0" 0 1 2 3
