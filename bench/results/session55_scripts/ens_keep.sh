# session 55: session 54's ensemble-guided flow (ens_seed.sh: λ 0.3, 5-member guide, κ) on one button-press seed with
# the readers reading into bench/results/readers_s55, then BC with the top-k kept (bc.keep_top_k=true) on BC seeds
# given (session 53 bc_spread.sh, TAG=keeptopk), copies of every run's metrics.json/report.md in readers_s55/runs/.
# usage: [T=<task> N=<noise>] [READ=none] bash ens_keep.sh SEED KAPPA BC_SEED [BC_SEED ...]   (venv active; one core;
#   READ=none skips the readers reading)
S=$1; K=$2; shift 2
D=$(dirname "$0"); KEEP=bench/results/readers_s55/runs; mkdir -p $KEEP
KEEP=$KEEP bash $D/../session54_scripts/ens_seed.sh $S $K ${READ:-bench/results/readers_s55} || exit 1
E=/work/runs/room_s54/${T:-button-press-v3}_e${N:-4}_s${S}_v4500_sg0.3_ens5k$K
G="diffuser.score_guidance=0.3 diffuser.score_guidance_members=5 diffuser.score_guidance_kappa=$K"
TAG=keeptopk KEEP=$KEEP bash $D/../session53_scripts/bc_spread.sh $E "$G bc.keep_top_k=true" "$@"
