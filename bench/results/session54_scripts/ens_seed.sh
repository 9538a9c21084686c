# session 54: the ensemble-guided flow (diffuser.score_guidance=L, default 0.3, score_guidance_members=5, score_guidance_kappa=K)
# on one seed of a task's data with room, from a fresh machine: rebuild the run up to the diffuser (session 52
# rebuild.sh: a finished rebuild is kept, a partial one resumed), redo it from the flow with the guide (session 52
# variant.sh: flow, BC, evaluation, open-loop replay, then the readers reading unless READ_DIR is none), copy its
# metrics.json and report.md to KEEP/<name>/, then BC seeds (session 53 bc_spread.sh, whose copies go there too).
# usage: bash ens_seed.sh SEED KAPPA READ_DIR|none [BC_SEED ...]   (venv active; one core)
#   environment (session 55): T=<task> N=<action noise> (default button-press-v3, 4); KEEP=<dir> (default
#   bench/results/readers_s54/runs); BC="<overrides>" added to the BC seeds' runs only, TAG=<name> naming their copies
#   (bc_spread.sh's); L=<guidance scale> (session 56; default 0.3)
#   -> /work/runs/room_s54/<T>_e<N>_s<SEED>_v4500_sg<L>_ens5k<KAPPA>
S=$1; K=$2; RD=$3; shift 3
D=$(dirname "$0"); L=${L:-0.3}; T=${T:-button-press-v3}; N=${N:-4}; KEEP=${KEEP:-bench/results/readers_s54/runs}
W=/work/runs/room_s52/${T}_e${N}_s${S}_v4500; mkdir -p /work/runs/room_s53 /work/runs/room_s54
bash $D/../session52_scripts/rebuild.sh $T $N $S 4500 || exit 1
G="diffuser.score_guidance=$L diffuser.score_guidance_members=5 diffuser.score_guidance_kappa=$K"
NAME=sg${L}_ens5k$K; E=/work/runs/room_s54/$(basename $W)_$NAME
OUT=/work/runs/room_s54 READ=$RD bash $D/../session52_scripts/variant.sh $W $NAME $G || { echo "failed: $E"; exit 1; }
mkdir -p $KEEP/$(basename $E) && cp $E/metrics.json $E/report.md $KEEP/$(basename $E)/
python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print(sys.argv[2], m['guide'], m['eval']['success_rate'])" \
  $E/metrics.json $(basename $E)
[ $# -gt 0 ] || exit 0
KEEP=$KEEP bash $D/../session53_scripts/bc_spread.sh $E "$G${BC:+ $BC}" "$@"
