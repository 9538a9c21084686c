#!/bin/bash
# Session 36: the README's main command on the final code, idle machine, dataset cached first (the target's terms).
cd /work/main
.venv/bin/python recipes/make_dataset.py --env button-press-v3 --no-progress > /work/runs/readme_s36/make_dataset.log 2>&1
/usr/bin/time -v .venv/bin/python recipes/ftb_offline.py --config-name ftb_offline_metaworld labels.horizon=500 \
  progress=false run_dir=/work/runs/readme_s36/run > /work/runs/readme_s36/recipe.log 2> /work/runs/readme_s36/time_v.txt
