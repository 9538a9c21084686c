"""Session 51: what score guidance moves. Samples 16 top-block conditions of one run with and without
diffuser.score_guidance (same seed, DDPM, 20 steps, guidance 1.2) and reports the mean absolute per-step change of each
Meta-World observation group (cm; gripper and quaternion unitless), of the first step's hand, and the actions' size.

usage: python bench/results/session51_scripts/guide_dims.py RUN_DIR LAMBDA OUT.json   (venv active)
"""
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_diagnostics import load_run  # noqa: E402

from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.preference import load_score_model, score_objective  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

run, lam, out = Path(sys.argv[1]), float(sys.argv[2]), Path(sys.argv[3])
torch.set_num_threads(1)
cfg, trajs, _ = load_run(run, with_returns=True, horizon=500)
blocks = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)
scores, ids = blocks["scores"], blocks["block_ids"]
diffuser = load_diffuser(run / "checkpoints" / "diffuser" / "diffuser_last.pt")
objective = score_objective(load_score_model(run / "checkpoints" / "score_model.pt"), float(scores.min()),
                            float(scores.max()))
top = trajs[(ids == ids.max()).nonzero().squeeze(-1)[:16]]
samples = [diffuser.generate(top, sampler="ddpm", steps=20, guidance=1.2, generator=torch.Generator().manual_seed(0),
                             guide=objective if scale else None, guide_scale=scale) for scale in (0.0, lam)]
plain, guided = samples
mask = plain["mask"] & guided["mask"]
diff = (plain["observation"] - guided["observation"]).abs()[mask]
groups = {"hand_cm": slice(0, 3), "gripper": slice(3, 4), "object_cm": slice(4, 7), "object_quat": slice(7, 11),
          "previous_hand_cm": slice(18, 21), "previous_object_cm": slice(22, 25), "goal_cm": slice(36, 39)}
moved = {k: float(diff[:, v].mean()) * (100 if k.endswith("_cm") else 1) for k, v in groups.items()}
moved["first_step_hand_cm"] = 100 * float((plain["observation"][:, 0, :3] - guided["observation"][:, 0, :3])
                                          .norm(dim=-1).mean())
moved["action_abs_mean"] = [float(s["action"][s["mask"]].abs().mean()) for s in samples]
print(moved)
write_json(out, {**run_record(config={"run_dir": str(run), "score_guidance": lam, "conditions": 16, "sampler": "ddpm",
                                      "steps": 20, "guidance": 1.2, "seed": 0}), "moved": moved})
