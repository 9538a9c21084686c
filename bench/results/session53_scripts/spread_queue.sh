# session 53: the BC-spread queue on button-press seed 4 (one core): the paper's flow without and with the
# penetration check, and the guided flows with the check, each with BC seeds 0-3 (the run's own BC seed is 4).
cd /work/main && . .venv/bin/activate
D=bench/results/session53_scripts; R52=/work/runs/room_s52; BASE=$R52/button-press-v3_e4_s4_v4500
bash $D/flow_only.sh $BASE sg0 diffuser.score_guidance=0
bash $D/bc_spread.sh /work/runs/room_s53/button-press-v3_e4_s4_v4500_sg0 "diffuser.score_guidance=0" 0 1 2 3
bash $D/bc_spread.sh $R52/button-press-v3_e4_s4_v4500_sg0_pen0 "diffuser.score_guidance=0 flow.max_hand_penetration=0" 0 1 2 3
bash $D/bc_spread.sh $R52/button-press-v3_e4_s4_v4500_sg0.1_pen0 "diffuser.score_guidance=0.1 flow.max_hand_penetration=0" 0 1 2 3
bash $D/bc_spread.sh $R52/button-press-v3_e4_s4_v4500_sg0.3_pen0 "diffuser.score_guidance=0.3 flow.max_hand_penetration=0" 0 1 2 3
