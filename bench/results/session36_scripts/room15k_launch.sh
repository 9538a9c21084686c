#!/bin/bash
# Session 36: session 32's drawer-open eps=8 headroom cell (seed 4) with 15,000 diffuser steps instead of 4,500.
cd /work/main
.venv/bin/python bench/table1.py --methods ftb --tasks drawer-open-v3 --teacher success --seeds 4 --threads 2 \
  --results-dir bench/results/table1_v2_headroom_s36_room15k --runs-dir /work/runs/room_s36/cells \
  --extra score_model.horizon=500 flow.top_k=200 flow.true_return_horizon=500 eval.num_episodes=50 \
  diffuser.observation_structure=true flow.max_hand_model_error=0.01 flow.max_contactless_object_path=1x \
  diffuser.steps=15000 dataset.noise=8 'dataset.groups=[expert,within,random]' flow.true_return_streak=25 \
  analysis.tracked=true tracker.candidates=1 diffuser.checkpoint_every=1000
