# session 43: what the v diffuser of a room run makes of each block's conditions (bench/diffuser_conditioning.py,
# 16 conditions per block, the top block too, stop-rule returns), at the run's own 4,500 steps and trained on to
# 9,000 on the run's own pairs (evaluated every 1,500). usage: bash cond.sh RUN_DIR TAG   (one core; as run on
# /work/runs/room_s43/drawer-open-v3_e8_s4_v4500 with TAG room-v4500-s43, then room-v4500to9000-s43 with LONG=1;
# those two used the scratch work dirs /work/runs/room_s43/do8_s4_{own4500,long}, which hold only a checkpoint copy;
# also run on /work/runs/room_s43/sweep-into-v3_e8_s6_v4500 with TAG room-v4500-s43, work dir .../si8_s6_own4500)
RUN=$1; TAG=$2
export OMP_NUM_THREADS=1
A="--run-dir $RUN --per-block 16 --top-block --horizon 500 --streak 25 --tag $TAG"
if [ -z "$LONG" ]; then
  python bench/diffuser_conditioning.py $A --steps 4500 --work-dir ${RUN}_own4500
else
  python bench/diffuser_conditioning.py $A --steps 9000 --eval-every 1500 --work-dir ${RUN}_long
fi
