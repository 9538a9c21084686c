# session 42: another seed of room.sh's comparison of the policy: v prediction from the start (no epsilon run), then
# BC on s_psi's top-k alone (a copy redone from the flow with flow.flow_steps=0); 50 evaluation episodes each.
# usage: bash room_seed.sh TASK NOISE SEED [STEPS]   (one core; STEPS: diffuser steps, default the preset's 1,500;
# runs under /work/runs/room_s42/TASK_s<SEED>_{v,topk}, with STEPS given TASK_s<SEED>_{v,topk}<STEPS>)
T=$1; N=$2; S=$3; R=/work/runs/room_s42; X=""; D=""
[ -n "$4" ] && X="diffuser.steps=$4" && D=$4
C="--config-name ftb_offline_metaworld labels.horizon=500 env.name=$T seed=$S dataset.noise=$N"
C="$C dataset.groups=[expert,within,random] progress=false eval.num_episodes=50 $X"
V="diffuser.overrides={prediction_type:v_prediction}"
export OMP_NUM_THREADS=1
python recipes/ftb_offline.py $C run_dir=$R/${T}_s${S}_v$D "$V" > $R/${T}_s${S}_v$D.log 2>&1 || exit 1
cp -r $R/${T}_s${S}_v$D $R/${T}_s${S}_topk$D
python recipes/ftb_offline.py $C run_dir=$R/${T}_s${S}_topk$D resume=true redo_from=flow flow.flow_steps=0 "$V" \
  > $R/${T}_s${S}_topk$D.log 2>&1 || exit 1
