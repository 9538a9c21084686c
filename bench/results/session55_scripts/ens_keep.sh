# session 55: session 54's ensemble-guided flow (ens_seed.sh: λ 0.3, 5-member guide, κ) on one seed with the readers
# reading into bench/results/readers_s55, then BC with the top-k kept (bc.keep_top_k=true, copies tagged keeptopk) on
# the BC seeds given; copies of every run's metrics.json/report.md in readers_s55/runs/.
# usage: [T=<task> N=<noise>] [READ=none] bash ens_keep.sh SEED KAPPA BC_SEED [BC_SEED ...]   (venv active; one core;
#   READ=none skips the readers reading)
S=$1; K=$2; shift 2
KEEP=bench/results/readers_s55/runs BC=bc.keep_top_k=true TAG=keeptopk \
  bash "$(dirname "$0")/../session54_scripts/ens_seed.sh" $S $K ${READ:-bench/results/readers_s55} "$@"
