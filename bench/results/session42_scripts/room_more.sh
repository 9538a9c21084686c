# session 42: the policy beside room.sh's runs, 50 evaluation episodes each: BC on s_psi's top-k alone (no flow:
# the epsilon run redone from the flow with flow.flow_steps=0), and the epsilon and v runs evaluated again.
# usage: bash room_more.sh TASK NOISE   (one core; after room.sh TASK NOISE)
T=$1; N=$2; R=/work/runs/room_s42; S=4
C="--config-name ftb_offline_metaworld labels.horizon=500 env.name=$T seed=$S dataset.noise=$N"
C="$C dataset.groups=[expert,within,random] progress=false eval.num_episodes=50"
V="diffuser.overrides={prediction_type:v_prediction}"
export OMP_NUM_THREADS=1
cp -r $R/${T}_eps $R/${T}_topk
python recipes/ftb_offline.py $C run_dir=$R/${T}_topk resume=true redo_from=flow flow.flow_steps=0 \
  > $R/${T}_topk.log 2>&1 || exit 1
python recipes/ftb_offline.py $C run_dir=$R/${T}_eps resume=true redo_from=eval > $R/${T}_eps_eval50.log 2>&1 || exit 1
python recipes/ftb_offline.py $C run_dir=$R/${T}_v resume=true redo_from=eval "$V" > $R/${T}_v_eval50.log 2>&1 || exit 1
