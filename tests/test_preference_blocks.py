"""K-means score blocks and the pair samplers (paper Alg. 2 line 7, Eq. 5, Eq. 3)."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_ftb.preference import (
    BlockPairSampler,
    BlockWarning,
    make_block_pair_buffer,
    make_blocks,
    make_labeled_pair_buffer,
    standardized_starts,
)
from torchrl_ftb.testing import make_toy_dataset

KEYS = ("observation", "action", "mask")


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_trajectories=40, horizon=16, seed=0)


# --------------------------------------------------------------------------- blocks
def test_blocks_are_ascending_contiguous_and_deterministic():
    g = torch.Generator().manual_seed(0)
    scores = torch.cat([torch.randn(30, generator=g) * 0.3 + c for c in (0.0, 4.0, 8.0, 12.0, 16.0)])
    scores = scores[torch.randperm(scores.numel(), generator=g)]
    ids = make_blocks(scores, 5, seed=0)
    assert ids.dtype == torch.int64 and ids.shape == scores.shape
    assert set(ids.tolist()) == set(range(5))
    for k in range(4):  # every score of block k is below every score of block k+1
        assert scores[ids == k].max() < scores[ids == k + 1].min()
    # the five well-separated groups are recovered
    for c, k in zip((0.0, 4.0, 8.0, 12.0, 16.0), range(5)):
        assert bool(((scores[ids == k] - c).abs() < 2).all())
    torch.testing.assert_close(make_blocks(scores, 5, seed=0), ids)
    torch.testing.assert_close(make_blocks(scores.clone(), 5, seed=0, n_init=3), ids)


def test_blocks_degenerate_cases_warn_or_raise():
    with pytest.warns(BlockWarning, match="distinct"):
        ids = make_blocks(torch.tensor([1.0, 1.0, 2.0, 2.0, 3.0, 3.0]), 5)
    assert ids.tolist() == [0, 0, 1, 1, 2, 2]
    with pytest.warns(BlockWarning, match="distinct"):
        assert make_blocks(torch.full((4,), 7.0), 3).tolist() == [0, 0, 0, 0]
    # a lone outlier would be a singleton top block: merged into its neighbour
    with pytest.warns(BlockWarning, match="merged"):
        ids = make_blocks(torch.tensor([0.0, 0.1, 0.2, 5.0, 5.1, 5.2, 100.0]), 3)
    assert ids.tolist() == [0, 0, 0, 1, 1, 1, 1]
    # min_block_size=1 keeps it
    assert make_blocks(torch.tensor([0.0, 0.1, 0.2, 5.0, 5.1, 5.2, 100.0]), 3, min_block_size=1).tolist() == [0, 0, 0, 1, 1, 1, 2]
    with pytest.raises(ValueError, match="num_blocks"):
        make_blocks(torch.arange(3.0), 4)
    with pytest.raises(ValueError, match="NaN"):
        make_blocks(torch.tensor([0.0, float("nan"), 1.0]), 2)
    with pytest.raises(ValueError, match="1-D"):
        make_blocks(torch.zeros(2, 3), 2)
    assert make_blocks(torch.arange(5.0), 1).tolist() == [0] * 5


# --------------------------------------------------------------------------- block pairs
def test_block_pair_buffer_pairs_adjacent_blocks(toy):
    blocks = torch.tensor([0] * 5 + [1] * 20 + [2] * 15)[torch.randperm(40, generator=torch.Generator().manual_seed(1))]
    rb = make_block_pair_buffer(toy, blocks, batch_size=4000, seed=0)
    assert isinstance(rb, TensorDictReplayBuffer)
    batch = rb.sample()
    assert batch.batch_size == (4000,)
    assert batch["condition"].batch_size == (4000, 16) and batch["target"].batch_size == (4000, 16)
    i0, i1 = batch["index"].unbind(-1)
    k = batch["block"]
    assert bool((blocks[i0] == k).all()) and bool((blocks[i1] == k + 1).all())
    # the sub-tds are those trajectories
    torch.testing.assert_close(batch["condition", "observation"], toy["observation"][i0])
    torch.testing.assert_close(batch["target", "mask"], toy["mask"][i1])
    # k is uniform over the K-1 adjacent pairs (not proportional to block sizes)
    freq = torch.bincount(k, minlength=2).float() / k.numel()
    assert torch.allclose(freq, torch.tensor([0.5, 0.5]), atol=0.04)
    # within a block, members are drawn uniformly: every member of the small block 0 appears
    assert set(i0[k == 0].tolist()) == set(torch.nonzero(blocks == 0).flatten().tolist())
    # seeded buffers reproduce, different seeds differ
    a = make_block_pair_buffer(toy, blocks, batch_size=16, seed=3).sample()["index"]
    b = make_block_pair_buffer(toy, blocks, batch_size=16, seed=3).sample()["index"]
    c = make_block_pair_buffer(toy, blocks, batch_size=16, seed=4).sample()["index"]
    assert torch.equal(a, b) and not torch.equal(a, c)
    # extra keys on request (e.g. the reward when it is diffused), all keys with keys=None
    with_reward = make_block_pair_buffer(toy, blocks, batch_size=3, keys=[*KEYS, ("next", "reward")]).sample()
    assert with_reward["target", "next", "reward"].shape == (3, 16, 1)
    assert "quality" in make_block_pair_buffer(toy, blocks, batch_size=3, keys=None).sample()["condition"].keys()
    with pytest.raises(ValueError, match="have no"):
        make_block_pair_buffer(toy, blocks, batch_size=3, keys=[*KEYS, "state"])


def test_block_pair_buffer_errors(toy):
    with pytest.raises(ValueError, match="at least 2 blocks"):
        make_block_pair_buffer(toy, torch.zeros(40, dtype=torch.long), batch_size=4)
    with pytest.raises(ValueError, match="block_ids"):
        make_block_pair_buffer(toy, torch.zeros(39, dtype=torch.long), batch_size=4)
    with pytest.raises(ValueError, match="contiguous"):
        BlockPairSampler(torch.tensor([0, 0, 2, 2]))
    with pytest.raises(ValueError, match="mask"):
        make_block_pair_buffer(toy.exclude("mask"), torch.arange(40) % 2, batch_size=4)


def test_neighbour_pairs_stay_adjacent_and_start_nearest(toy):
    """``neighbours=m``: each condition is paired only with the m next-block trajectories starting nearest to it."""
    blocks = torch.tensor([0] * 12 + [1] * 16 + [2] * 12)[torch.randperm(40, generator=torch.Generator().manual_seed(1))]
    rb = make_block_pair_buffer(toy, blocks, batch_size=3000, seed=0, neighbours=3)
    batch = rb.sample()
    i0, i1 = batch["index"].unbind(-1)
    k = batch["block"]
    assert bool((blocks[i0] == k).all()) and bool((blocks[i1] == k + 1).all())
    starts = toy["observation"][:, 0]
    z = standardized_starts(starts)
    for a in i0.unique().tolist():
        nxt = torch.nonzero(blocks == blocks[a] + 1).squeeze(-1)
        nearest = set(nxt[torch.cdist(z[a:a + 1], z[nxt])[0].argsort()[:3]].tolist())
        assert set(i1[i0 == a].tolist()) <= nearest  # only its three nearest ...
    assert len(set(i1[i0 == i0[0]].tolist())) > 1  # ... drawn among them, not always the nearest one
    # the condition and its target start nearer each other than uniform pairs do
    uniform = make_block_pair_buffer(toy, blocks, batch_size=3000, seed=0).sample()["index"]
    def gap(idx):
        return (z[idx[:, 0]] - z[idx[:, 1]]).norm(dim=-1).mean()
    assert gap(batch["index"]) < 0.8 * gap(uniform)
    # m above a block's size: every member of the next block; seeded and reproducible; a state_dict round trip
    big = BlockPairSampler(blocks, neighbours=100, starts=starts)
    assert bool((big.neighbour_table[blocks == 0] >= 0).sum(1).eq(16).all())
    assert bool((big.neighbour_table[blocks == 2] == -1).all())  # the top block conditions nothing
    again = make_block_pair_buffer(toy, blocks, batch_size=64, seed=5, neighbours=3).sample()["index"]
    assert torch.equal(again, make_block_pair_buffer(toy, blocks, batch_size=64, seed=5, neighbours=3).sample()["index"])
    copy = BlockPairSampler(torch.zeros(2, dtype=torch.long) + torch.tensor([0, 1]))
    copy.load_state_dict(big.state_dict())
    assert copy.neighbours == 100 and torch.equal(copy.neighbour_table, big.neighbour_table)
    with pytest.raises(ValueError, match="neighbours needs starts"):
        BlockPairSampler(blocks, neighbours=2)
    with pytest.raises(ValueError, match="neighbours must be >= 1"):
        BlockPairSampler(blocks, neighbours=0, starts=starts)
    with pytest.raises(ValueError, match="starts must be finite"):
        BlockPairSampler(blocks, neighbours=2, starts=starts[:5])


def test_block_weights_choose_the_transitions(toy):
    """``block_weights``: transitions drawn in proportion to their weight; zero-weight ones never; checked input."""
    blocks = torch.arange(40) % 5
    batch = make_block_pair_buffer(toy, blocks, batch_size=4000, seed=0, block_weights=[0, 0, 1, 3]).sample()
    i0, i1 = batch["index"].unbind(-1)
    counts = torch.bincount(batch["block"], minlength=4)
    assert counts[:2].tolist() == [0, 0] and 2.5 < counts[3] / counts[2] < 3.5  # 1 : 3
    assert bool((blocks[i0] == batch["block"]).all()) and bool((blocks[i1] == batch["block"] + 1).all())
    # with neighbours too; seeded; the weights survive a state_dict round trip
    starts = toy["observation"][:, 0]
    near = BlockPairSampler(blocks, neighbours=2, starts=starts, block_weights=[1, 0, 0, 0])
    copy = BlockPairSampler(blocks)
    copy.load_state_dict(near.state_dict())
    assert torch.equal(copy.block_weights, torch.tensor([1.0, 0.0, 0.0, 0.0]))
    pair = make_block_pair_buffer(toy, blocks, batch_size=64, seed=3, neighbours=2, block_weights=[1, 0, 0, 0])
    assert bool((pair.sample()["block"] == 0).all())
    for bad in ([1, 1], [0, 0, 0, 0], [1, -1, 1, 1], [1, float("nan"), 1, 1]):
        with pytest.raises(ValueError, match="block_weights must be 4"):
            BlockPairSampler(blocks, block_weights=bad)


def test_top_block_pairs_condition_on_the_top_block_and_target_a_better_member(toy):
    """``top_block_scores``: a K-th kind of pair inside the top block, condition below target by the score, drawn
    as often as each transition; the best member is never a condition; with neighbours the nearest better ones."""
    blocks = torch.arange(40) % 5  # 8 per block
    scores = torch.randn(40, generator=torch.Generator().manual_seed(0))
    batch = make_block_pair_buffer(toy, blocks, batch_size=5000, seed=0, top_block_scores=scores).sample()
    i0, i1 = batch["index"].unbind(-1)
    own = blocks[i0] == 4
    counts = torch.bincount(batch["block"], minlength=5)
    assert counts.min() > 800 and bool((batch["block"] == blocks[i0]).all())  # five kinds, about 1,000 each
    assert bool((blocks[i1][~own] == blocks[i0][~own] + 1).all())  # the other pairs are Eq. 5's
    assert bool((blocks[i1][own] == 4).all()) and bool((scores[i1][own] > scores[i0][own]).all())
    top = torch.nonzero(blocks == 4).squeeze(-1)
    best, worst = top[scores[top].argmax()], top[scores[top].argmin()]
    assert int((i0[own] == best).sum()) == 0 and int((i1[own] == worst).sum()) == 0
    assert set(i0[own].tolist()) == set(top.tolist()) - {int(best)}  # every other member conditions
    assert set(i1[own].tolist()) == set(top.tolist()) - {int(worst)}  # every better one is a target
    # off: the paper's adjacent pairs, seeded
    plain = make_block_pair_buffer(toy, blocks, batch_size=64, seed=1).sample()["index"]
    assert torch.equal(plain, make_block_pair_buffer(toy, blocks, batch_size=64, seed=1).sample()["index"])
    assert bool((blocks[plain[:, 1]] == blocks[plain[:, 0]] + 1).all())
    # with neighbours: a top condition's target is one of its m nearest better members
    starts = toy["observation"][:, 0]
    near = BlockPairSampler(blocks, neighbours=2, starts=starts, top_block_scores=scores)
    assert bool((near.neighbour_table[best] == -1).all())
    z = standardized_starts(starts)
    for a in top.tolist():
        better = top[scores[top] > scores[a]]
        want = set(better[torch.cdist(z[a:a + 1], z[better])[0].argsort()[:2]].tolist()) if better.numel() else set()
        assert set(near.neighbour_table[a][near.neighbour_table[a] >= 0].tolist()) == want
    idx = make_block_pair_buffer(toy, blocks, batch_size=2000, seed=2, neighbours=2, top_block_scores=scores,
                                 block_weights=[0, 0, 0, 0, 1]).sample()["index"]
    assert bool((blocks[idx] == 4).all()) and bool((scores[idx[:, 1]] > scores[idx[:, 0]]).all())
    copy = BlockPairSampler(blocks)
    copy.load_state_dict(near.state_dict())
    assert copy.top_pairs and torch.equal(copy.neighbour_table, near.neighbour_table)
    with pytest.raises(ValueError, match="block_weights must be 5 .* top block's own pairs"):
        BlockPairSampler(blocks, top_block_scores=scores, block_weights=[1, 1, 1, 1])
    with pytest.raises(ValueError, match="top_block_scores must be finite"):
        BlockPairSampler(blocks, top_block_scores=scores[:5])
    with pytest.raises(ValueError, match="top block of >= 2"):
        BlockPairSampler(torch.tensor([0, 0, 1]), top_block_scores=torch.zeros(3))


# --------------------------------------------------------------------------- labelled pairs
def test_labeled_pair_buffer_orders_worse_to_better_and_skips_ties(toy):
    ret = toy["next", "reward"].squeeze(-1).sum(-1)
    i0, i1 = torch.arange(0, 20), torch.arange(20, 40)
    label = (ret[i1] > ret[i0]).float()
    label[:3] = 0.5
    labels = TensorDict({"tau0": toy[i0].select(*KEYS), "tau1": toy[i1].select(*KEYS), "label": label}, [20])
    rb = make_labeled_pair_buffer(labels, batch_size=500, seed=0)
    assert len(rb) == 17
    batch = rb.sample()
    assert batch["condition"].batch_size == (500, 16)
    # identify each sampled trajectory by its observations and check it is the worse one
    obs = toy["observation"]

    def which(x):
        return (obs[None] == x[:, None]).flatten(2).all(-1).float().argmax(-1)

    worse, better = which(batch["condition", "observation"]), which(batch["target", "observation"])
    assert bool((ret[worse] < ret[better]).all())
    tie_members = set(i0[:3].tolist()) | set(i1[:3].tolist())
    assert not (set(worse.tolist()) | set(better.tolist())) & tie_members
    ties = labels.clone()
    ties["label"] = torch.full((20,), 0.5)
    with pytest.raises(ValueError, match="ties"):
        make_labeled_pair_buffer(ties, batch_size=4)
