# session 56: does the README's main command still give session 48's final table at this commit (sessions 51-55 added
# score guidance, its ensemble and bc.keep_top_k, all off by default)? Runs the README command under /usr/bin/time -v
# into /work/runs/readme_s56/run and writes bench/results/readme_main_s56/{time_v.txt,check.json}: provenance,
# peak RSS, stage times, the final table and whether it equals session 50's (= session 48's) line for line, wall time
# and run-dir lines aside.
# usage: bash bench/results/session56_scripts/readme_check.sh   (repo root, venv active)
set -e
O=bench/results/readme_main_s56; W=/work/runs/readme_s56/run; mkdir -p $O /work/runs/readme_s56; rm -rf $W
CMD=".venv/bin/python recipes/ftb_offline.py --config-name ftb_offline_metaworld labels.horizon=500 run_dir=$W progress=false"
/usr/bin/time -v -o $O/time_v.txt $CMD > /work/runs/readme_s56/stdout.txt 2>&1
python3 - "$O" "$W" "/usr/bin/time -v $CMD" <<'PY'
import json, re, sys
from torchrl_ftb.provenance import run_record, write_json
out, run, cmd = sys.argv[1:]
m = json.load(open(f"{run}/metrics.json"))
lines = open("/work/runs/readme_s56/stdout.txt").read().splitlines()
start = next(i for i, l in enumerate(lines) if l.startswith("env "))
table = [l.rstrip() for l in lines[start:] if l.strip()]
ref = json.load(open("bench/results/readme_main_s50/check.json"))
skip = ("wall time", "run dir")
same = [l for l in table if not l.startswith(skip)] == [l.rstrip() for l in ref["final_table"] if not l.startswith(skip)]
tv = open(f"{out}/time_v.txt").read()
rec = {**run_record(command=cmd, config={"readme_main": True, "note": "the README's main command at this commit, "
                                         "checked against session 50's table (session 48's)"}),
       "elapsed": re.search(r"Elapsed .*: (\S+)", tv).group(1),
       "max_rss_kb": int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", tv).group(1)),
       "stage_time_s": m["stage_time_s"], "wall_time_s": m["wall_time_s"], "success_rate": m["eval"]["success_rate"],
       "final_table": table, "same_table_as_session_50": same, "session_50_run": "bench/results/readme_main_s50/check.json"}
write_json(f"{out}/check.json", rec)
print("same table as session 50:", same, "| success", rec["success_rate"], "| elapsed", rec["elapsed"])
PY
