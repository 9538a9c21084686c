#!/bin/bash
# score-model stage time, README command, stop_after=score_model: current HEAD vs session 30's bf676aa, one after the other
cd /work/main
for tree in /work/main /tmp/wt30; do
  tag=$(basename $tree); rm -rf /work/runs/readme_s36/ab_$tag
  ( cd $tree && PYTHONPATH=$tree /work/main/.venv/bin/python recipes/ftb_offline.py --config-name ftb_offline_metaworld labels.horizon=500 \
    progress=false run_dir=/work/runs/readme_s36/ab_$tag stop_after=score_model > /work/runs/readme_s36/ab_$tag.log 2>&1 )
  python3 -c "import json; d=json.load(open('/work/runs/readme_s36/ab_$tag/metrics_partial.json')); print('$tag', {k: round(v,1) for k,v in d['stage_time_s'].items()})"
done
