# session 42: the README configuration (return teacher, 30 labels, seed 4) on data with room above it
# (session 27's: dataset.noise=<eps>, no cross-task episodes), run with epsilon, then redone from the
# diffuser with v prediction (the same labels, s_psi and blocks), then v trained on to 4,500 steps.
# usage: bash room.sh TASK NOISE   (one core; runs under /work/runs/room_s42/TASK_{eps,v,v4500})
T=$1; N=$2; R=/work/runs/room_s42; S=4
C="--config-name ftb_offline_metaworld labels.horizon=500 env.name=$T seed=$S dataset.noise=$N"
C="$C dataset.groups=[expert,within,random] progress=false"
V="diffuser.overrides={prediction_type:v_prediction}"
export OMP_NUM_THREADS=1
python recipes/ftb_offline.py $C run_dir=$R/${T}_eps > $R/${T}_eps.log 2>&1 || exit 1
cp -r $R/${T}_eps $R/${T}_v
python recipes/ftb_offline.py $C run_dir=$R/${T}_v resume=true redo_from=diffuser "$V" > $R/${T}_v.log 2>&1 || exit 1
cp -r $R/${T}_v $R/${T}_v4500
python recipes/ftb_offline.py $C run_dir=$R/${T}_v4500 resume=true "$V" diffuser.steps=4500 \
  > $R/${T}_v4500.log 2>&1 || exit 1
