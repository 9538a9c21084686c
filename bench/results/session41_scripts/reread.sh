# session 41: evaluate a work dir's checkpoint once more (no training: --steps = its step), new tag.
# usage: bash reread.sh WORKDIR_NAME STEPS NEWTAG [--pairs copy] -- [override...]
R=/work/runs/readme_s36/run
X="--per-block 16 --top-block --horizon 500 --streak 25"
W=$1; STEPS=$2; TAG=$3; shift 3
EXTRA=""; while [ $# -gt 0 ] && [ "$1" != "--" ]; do EXTRA="$EXTRA $1"; shift; done; [ "$1" = "--" ] && shift
OV=""; [ $# -gt 0 ] && OV="--override $*"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 --hold $EXTRA $OV \
  --steps $STEPS --eval-every 3000 $X --work-dir /work/runs/skip_s41/$W --tag $TAG-s41
