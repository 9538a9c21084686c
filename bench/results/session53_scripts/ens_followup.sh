# session 53: after the ensemble-guided flow (variant.sh ... sg0.3_ens5k1): BC's spread on its set (BC seeds 0-3),
# then the same flow guided by the ensemble's mean (kappa 0) instead of its pessimistic bound, reusing the trained guide
# ensemble (a copy of the run redone from the flow), with its BC.
# usage: bash ens_followup.sh   (venv active; one core)
D=$(dirname "$0"); R=/work/runs/room_s53; E=$R/button-press-v3_e4_s4_v4500_sg0.3_ens5k1
G="diffuser.score_guidance=0.3 diffuser.score_guidance_members=5"
bash $D/bc_spread.sh $E "$G diffuser.score_guidance_kappa=1" 0 1 2 3
T=button-press-v3; N=4; S=4
. $D/../session43_scripts/common.sh
W=$R/button-press-v3_e4_s4_v4500_sg0.3_ens5k0
rm -rf $W && cp -r $E $W
python recipes/ftb_offline.py $C diffuser.steps=4500 run_dir=$W resume=true redo_from=flow analysis.tracked=false \
  analysis.open_loop=false "$V" $G diffuser.score_guidance_kappa=0 > $W.log 2>&1
python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print('kappa 0', m['guide'], m['eval']['success_rate'])" \
  $W/metrics.json
