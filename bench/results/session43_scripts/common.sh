# session 43: the one argument block every session-43 script sources (session 42's scripts repeated it).
# Inputs: T (task), N (action noise), S (seed). Sets R (runs dir), C (recipe overrides: the README configuration on
# data with room: return teacher, labels.horizon=500, expert/within/random groups, 50 evaluation episodes) and
# V (v prediction). One core per job.
R=/work/runs/room_s43
C="--config-name ftb_offline_metaworld labels.horizon=500 env.name=$T seed=$S dataset.noise=$N"
C="$C dataset.groups=[expert,within,random] progress=false eval.num_episodes=50"
V="diffuser.overrides={prediction_type:v_prediction}"
export OMP_NUM_THREADS=1
