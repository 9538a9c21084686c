# session 41: the copy task (target = condition) on held trajectories, stride 5, as session 40's copy.sh, with the
# condition encoder's linear skip (encoder_skip=true). usage: bash copy.sh TAG [override...]
R=/work/runs/readme_s36/run
X="--per-block 16 --top-block --horizon 500 --streak 25"
TAG=$1; shift
OV=""; [ $# -gt 0 ] && OV="--override $*"
OMP_NUM_THREADS=1 python bench/diffuser_conditioning.py --run-dir $R --preset cpu --stride 5 --hold --pairs copy $OV \
  --steps 9000 --eval-every 3000 $X --work-dir /work/runs/skip_s41/$TAG --tag $TAG-s41
