"""Session 37 probe: do a full-state inverse-dynamics model's actions make a Table-2 FTB supplement execute better?

Fits torchrl_ftb.policy.PathTracker with dims = every observation dimension on the hopper-medium-replay
analogue (offline, the data's transitions), relabels the actions of the 6,000-step FTB supplements of seeds 0
and 1 (and the data's top 20, as a fidelity check), and replays each set open loop; dynamics error against the
simulator as the recipe reports it.

    python bench/results/session37_scripts/relabel_probe.py --steps 4000 --supplements s0=PATH s1=PATH \
        --out bench/results/table2_s37_readings/relabel_probe.json
"""
import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.analysis import dynamics_error, locomotion_replays  # noqa: E402
from torchrl_ftb.augmentation import load_supplement  # noqa: E402
from torchrl_ftb.data import true_return  # noqa: E402
from torchrl_ftb.datasets import make_dataset  # noqa: E402
from torchrl_ftb.envs import dynamics_oracle  # noqa: E402
from torchrl_ftb.policy import fit_path_tracker  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

parser = argparse.ArgumentParser()
parser.add_argument("--steps", type=int, default=4000)
parser.add_argument("--supplements", nargs="+", required=True, metavar="LABEL=PATH")
parser.add_argument("--out", type=Path, required=True)
args = parser.parse_args()
data, _ = make_dataset("hopper", kind="medium-replay", progress=False)
t0 = time.time()
tracker = fit_path_tracker(data, steps=args.steps, dims=tuple(range(data["observation"].shape[-1])), seed=0)
rows = {"fit_s": time.time() - t0}
oracle = dynamics_oracle("hopper")
sets = {"top20": data[true_return(data).argsort(descending=True)[:20]]}
sets.update({label: load_supplement(path)[0] for label, path in (s.split("=", 1) for s in args.supplements)})
for label, t in sets.items():
    for name, x in (("own", t), ("relabelled", tracker.relabel(t))):
        r, _ = locomotion_replays("hopper", x)
        rows[f"{label}_{name}"] = {"open_loop_mean": float(r.mean()), "open_loop_max": float(r.max()),
                                  "dynamics_error": dynamics_error(x, oracle)["mean"]}
        print(label, name, rows[f"{label}_{name}"], flush=True)
write_json(args.out, {**run_record(config={k: str(v) for k, v in vars(args).items()}), "results": rows})
