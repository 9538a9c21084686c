# session 41: FTB's block pairs on held trajectories, stride 5 (as session 40's hold runs), with model overrides.
# usage: bash ftb.sh TAG STEPS [--pair-neighbours M] -- [override...]
R=/work/runs/readme_s36/run
X="--per-block 16 --top-block --horizon 500 --streak 25"
TAG=$1; STEPS=$2; shift 2
EXTRA=""; while [ $# -gt 0 ] && [ "$1" != "--" ]; do EXTRA="$EXTRA $1"; shift; done; [ "$1" = "--" ] && shift
OV=""; [ $# -gt 0 ] && OV="--override $*"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 --hold $EXTRA $OV \
  --steps $STEPS --eval-every 3000 $X --work-dir /work/runs/skip_s41/$TAG --tag $TAG-s41
