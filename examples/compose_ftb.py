"""FTB composed from torchrl_ftb's TorchRL pieces in a few lines (toy task, runs in ~1 minute).

    python examples/compose_ftb.py

Each stage is a TorchRL object you can drop into your own pipeline: the score model is a
TensorDictModule, its loss a LossModule, block pairs come from a TensorDictReplayBuffer,
the diffuser sampler is a TensorDictModule (``"condition"`` -> ``"sample"``), and the flowed
set lands in a ReplayBuffer for BC.
"""
import tempfile
from pathlib import Path

import torch

from torchrl_ftb.data import ReturnTeacher, make_scripted_labels
from torchrl_ftb.diffusion import DiffusionSampler, make_diffuser, train_diffuser
from torchrl_ftb.flow import FlowToBetter
from torchrl_ftb.policy import evaluate_policy, make_bc_actor, train_bc
from torchrl_ftb.preference import (
    ScoreModel,
    load_score_model,
    make_block_pair_buffer,
    make_blocks,
    save_score_model,
    score_trajectories,
    train_score_model,
)
from torchrl_ftb.testing import ToyLineEnv, make_toy_dataset, toy_reward


def main() -> None:
    torch.manual_seed(0)
    trajs = make_toy_dataset(num_trajectories=128, horizon=32, seed=0)  # [N, H] + mask
    labels = make_scripted_labels(trajs, num_pairs=30, teacher=ReturnTeacher(), seed=0)

    # 1. preference augmentation: Bradley-Terry score model -> K ascending blocks
    score_model = ScoreModel(3, 2, num_cells=64, seed=0).fit_normalizer(trajs)  # r_psi on z-scored obs
    train_score_model(score_model, labels, steps=300, lr=1e-3, eval_fraction=0.0, progress=False)
    with tempfile.TemporaryDirectory() as tmp:  # checkpoints load with torch.load(weights_only=True)
        score_model = load_score_model(save_score_model(score_model, Path(tmp) / "score_model.pt"))
    scores = score_trajectories(score_model, trajs)
    blocks = make_blocks(scores, 5, seed=0)

    # 2. conditional trajectory diffuser trained on adjacent-block pairs
    diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=32, data=trajs)  # fits the normaliser
    pairs = make_block_pair_buffer(trajs, blocks, batch_size=32, seed=0)
    train_diffuser(diffuser, pairs, steps=300, lr=3e-3, grad_clip=1.0, progress=False)

    # 3. flow to better from the top-k
    sampler = DiffusionSampler(diffuser, sampler="ddpm", steps=25, generator=torch.Generator().manual_seed(0))
    flow = FlowToBetter(sampler, score_model, top_k=32, num_blocks=5, max_flow_steps=3,
                        true_reward_fn=toy_reward, progress=False)
    result = flow(trajs, scores=scores, block_ids=blocks)
    print("top-k true return before/after:",
          float(result.original_true_returns.mean()), float(result.true_returns.mean()))

    # 4. policy extraction by behaviour cloning, evaluated in a torchrl env
    actor = make_bc_actor(3, 2, hidden=(64, 64))
    train_bc(actor, flow.to_replay_buffer(result, batch_size=256), steps=1000, lr=1e-3, progress=False)
    print(evaluate_policy(lambda: ToyLineEnv(max_steps=32), actor, num_episodes=5, max_steps=32))


if __name__ == "__main__":
    main()
