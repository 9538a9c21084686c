#!/bin/bash
# Session 36: the run as it would have ended with diffuser.steps=N. The diffuser trains at a constant LR with the
# pair stream in its checkpoint, so the 15,000-step run's checkpoint at step N is exactly an N-step training.
# Rebuild the run as it stood when that checkpoint was written (stages up to blocks done, the step-N checkpoint in
# place, as if killed there), then resume it with diffuser.steps=N: the recipe finishes the diffuser at N (nothing to
# train) and runs the flow, BC, evaluation and analysis.
set -e
N=$1; THREADS=${2:-1}
SRC=/work/runs/room_s36/cells/drawer-open-v3/success/ftb/seed4
DST=/work/runs/room_s36/at_$N/seed4
mkdir -p $DST
cp -a $SRC/. $DST/
rm -rf $DST/checkpoints/diffuser $DST/checkpoints/flow.pt $DST/checkpoints/bc.pt $DST/metrics*.json $DST/report.md \
  $DST/plots
mkdir -p $DST/checkpoints/diffuser
cp /work/runs/room_s36/snap_$N/diffuser_last.pt $DST/checkpoints/diffuser/diffuser_last.pt
python3 - "$DST" <<'PY'
import json, sys
d = sys.argv[1]
st = json.load(open(f"{d}/stages.json"))
json.dump({k: v for k, v in st.items() if k in ("dataset", "labels", "score_model", "blocks")},
          open(f"{d}/stages.json", "w"), indent=2)
PY
cd /work/main
OMP_NUM_THREADS=$THREADS .venv/bin/python recipes/ftb_offline.py env.name=drawer-open-v3 seed=4 labels.teacher=success \
  preset=cpu run_dir=$DST resume=true progress=false score_model.horizon=500 flow.top_k=200 flow.true_return_horizon=500 \
  eval.num_episodes=50 diffuser.observation_structure=true flow.max_hand_model_error=0.01 \
  flow.max_contactless_object_path=1x diffuser.steps=$N dataset.noise=8 'dataset.groups=[expert,within,random]' \
  flow.true_return_streak=25 analysis.tracked=true tracker.candidates=1 diffuser.checkpoint_every=1000
