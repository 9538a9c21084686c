# session 42: room.sh's last stage alone (v trained on to 4,500 steps), for a task whose chain was stopped before it
# (drawer-open: stopped to free the core for sweep-into's chain). usage: bash room_v4500.sh TASK NOISE
T=$1; N=$2; R=/work/runs/room_s42; S=4
C="--config-name ftb_offline_metaworld labels.horizon=500 env.name=$T seed=$S dataset.noise=$N"
C="$C dataset.groups=[expert,within,random] progress=false eval.num_episodes=50"  # as room_more.sh left the v run
V="diffuser.overrides={prediction_type:v_prediction}"
export OMP_NUM_THREADS=1
rm -rf $R/${T}_v4500 && cp -r $R/${T}_v $R/${T}_v4500
python recipes/ftb_offline.py $C run_dir=$R/${T}_v4500 resume=true "$V" diffuser.steps=4500 \
  > $R/${T}_v4500.log 2>&1 || exit 1
