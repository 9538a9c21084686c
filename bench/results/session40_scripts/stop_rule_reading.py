"""Session 40: does the success-streak stop rule fire in the generated states of a conditioning-bench model's
top-block samples? The same 16 top-block conditions as bench/diffuser_conditioning.py --top-block (its seeded pick),
one DDPM-25 sample each (guidance 1.2, the run's), refined from the model's stride to 500 steps; per trajectory:
length, whether 25 consecutive successes occur (the rule that ended the recorded episodes), and the true return
with the stop-rule fill to 500 after that cut (the bench's --horizon 500 --streak 25).

usage: python bench/results/session40_scripts/stop_rule_reading.py CKPT OUT.json [--hold]
"""
import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))
from flow_diagnostics import load_run, sample_true_return  # noqa: E402

from torchrl_ftb.data import (coarsen_trajectories, hold_last_step, refine_trajectories,  # noqa: E402
                              success_streak_fired)
from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.envs import true_reward_fn  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

parser = argparse.ArgumentParser()
parser.add_argument("checkpoint")
parser.add_argument("out")
parser.add_argument("--hold", action="store_true", help="the model trained on held trajectories (--hold)")
parser.add_argument("--run-dir", default="/work/runs/readme_s36/run")
args = parser.parse_args()
torch.set_num_threads(1)
run = Path(args.run_dir)
cfg, trajs, returns = load_run(run, with_returns=True, horizon=500)
conditions = hold_last_step(trajs) if args.hold else trajs
ids = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)["block_ids"]
k = int(ids.max())
members = (ids == k).nonzero().squeeze(-1)
idx = members[torch.randperm(members.numel(), generator=torch.Generator().manual_seed(int(cfg.seed) + k))[:16]]
fn = true_reward_fn(str(cfg.env.name), with_success=True)
diffuser = load_diffuser(args.checkpoint)
step = int(torch.load(args.checkpoint, weights_only=True)["step"])
stride = trajs.batch_size[1] // diffuser.horizon
sample = diffuser.generate(coarsen_trajectories(conditions[idx], stride), sampler="ddpm", steps=25, guidance=1.2,
                           generator=torch.Generator().manual_seed(0)).to("cpu")
sample = refine_trajectories(sample.select("observation", "action", "mask"), stride, horizon=trajs.batch_size[1])


def reading(t):
    seen = []  # the oracle's success flags, from the one pass that also gives the returns

    def recording(observation, action):
        reward, success = fn(observation, action)
        seen.append(torch.as_tensor(success).reshape(-1).bool())
        return reward, success

    ret = sample_true_return(t, recording, horizon=500, streak=25)  # one call per non-empty trajectory, in order
    mask = t["mask"]
    success = torch.zeros(mask.shape, dtype=torch.bool)
    for i, flags in zip(mask.any(-1).nonzero().flatten().tolist(), seen):
        success[i, :flags.numel()] = flags
    fired = success_streak_fired(success, mask, streak=25)
    return {"length": mask.sum(-1).tolist(), "streak_fired": fired.tolist(),
            "true_return": [round(x, 1) for x in ret.tolist()], "fired_share": float(fired.double().mean()),
            "true_return_mean": float(ret.mean())}


record = {**run_record(config={**vars(args), "step": step, "stride": stride, "conditions": idx.tolist()}),
          "conditions": reading(trajs[idx]), "samples": reading(sample)}
write_json(args.out, record)
for name in ("conditions", "samples"):
    r = record[name]
    print(f"{name}: streak fired {r['fired_share']:.2f}, true return mean {r['true_return_mean']:.0f}")
