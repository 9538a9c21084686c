"""Which pairs get labelled: label_pairs, uniform vs active query selection (entropy, disagreement)."""
import pytest
import torch

from torchrl_ftb.data.labels import ReturnTeacher, label_pairs, make_scripted_labels, true_return
from torchrl_ftb.preference import make_query_labels, query_priority, select_queries
from torchrl_ftb.testing import make_toy_dataset

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_MODEL = {"num_cells": 16, "num_layers": 2}


@pytest.fixture(scope="module")
def trajs():
    return make_toy_dataset(num_trajectories=20, horizon=10, seed=3)


def _pairs(labels):
    return [tuple(sorted(p)) for p in zip(labels["index0"].tolist(), labels["index1"].tolist(), strict=True)]


def test_label_pairs_is_what_scripted_labels_assemble(trajs):
    ref = make_scripted_labels(trajs, num_pairs=7, teacher=ReturnTeacher(), seed=2)
    again = label_pairs(trajs, ref["index0"], ref["index1"], teacher=ReturnTeacher())
    for key in ("label", "index0", "index1", "start0", "start1", ("tau0", "observation"), ("tau1", "mask")):
        assert torch.equal(again[key], ref[key]), key
    ret = true_return(trajs)
    assert torch.equal(again["label"], (ret[ref["index1"]] > ret[ref["index0"]]).float())
    with pytest.raises(ValueError, match=r"indices must be in \[0, 20\)"):
        label_pairs(trajs, torch.tensor([0]), torch.tensor([20]), teacher=ReturnTeacher())
    with pytest.raises(ValueError, match="one shape"):
        label_pairs(trajs, torch.tensor([0, 1]), torch.tensor([2]), teacher=ReturnTeacher())


def test_priorities_ask_about_the_uncertain_and_the_contested_pairs():
    # members agree that 2 >> 0 and that 1 ~ 0; they disagree about 3 vs 0
    scores = torch.tensor([[0.0, 0.1, 8.0, 4.0], [0.0, -0.1, 8.0, -4.0]])
    i, j = torch.tensor([0, 0, 0]), torch.tensor([1, 2, 3])
    entropy = query_priority(scores, i, j, strategy="entropy")
    disagreement = query_priority(scores, i, j, strategy="disagreement")
    assert entropy.argmax() == 0 and disagreement.argmax() == 2
    assert entropy[1] < entropy[0] and disagreement[1] < disagreement[2]
    with pytest.raises(ValueError, match="needs an ensemble"):
        query_priority(scores[:1], i, j, strategy="disagreement")
    with pytest.raises(ValueError, match="unknown strategy"):
        query_priority(scores, i, j, strategy="margin")
    # asked pairs (either order) are never asked again; too few left is a clear error
    a, b = select_queries(scores[:1], count=2, strategy="entropy", asked=torch.tensor([[1, 0]]))
    assert (0, 1) not in list(zip(a.tolist(), b.tolist(), strict=True)) and bool((a < b).all())
    with pytest.raises(ValueError, match="only 5 candidates are left"):
        select_queries(scores, count=6, strategy="entropy", asked=torch.tensor([[0, 1]]))
    # one trajectory the members disagree about would fill a whole batch; distinct pairs do not
    contested = torch.stack([torch.arange(8.0), torch.arange(8.0)])
    contested[1, 0] = 20.0
    a, b = select_queries(contested, count=3, strategy="disagreement", distinct=False)
    assert bool((a == 0).all())
    a, b = select_queries(contested, count=3, strategy="disagreement")
    assert len(set(a.tolist() + b.tolist())) == 6 and (a == 0).sum() == 1
    a, b = select_queries(contested[:, :3], count=3, strategy="disagreement")  # no disjoint triple: filled
    assert len(set(zip(a.tolist(), b.tolist(), strict=True))) == 3
    # capped candidates: a uniform subset is scored
    a, b = select_queries(torch.randn(1, 50), count=3, strategy="entropy", max_candidates=100)
    assert a.shape == (3,) and bool((a < b).all())


def test_random_strategy_is_the_paper_protocol(trajs):
    ref = make_scripted_labels(trajs, num_pairs=9, teacher=ReturnTeacher(), seed=4)
    got = make_query_labels(trajs, num_pairs=9, teacher=ReturnTeacher(), seed=4)
    assert torch.equal(got["index0"], ref["index0"]) and torch.equal(got["label"], ref["label"])


@pytest.mark.parametrize("strategy", ["entropy", "disagreement"])
def test_active_labels_extend_the_uniform_start_without_repeats(trajs, strategy):
    kwargs = dict(num_pairs=14, teacher=ReturnTeacher(), seed=1, strategy=strategy, initial=6, per_round=4,
                  members=2, steps=20, model_kwargs=TINY_MODEL)
    labels = make_query_labels(trajs, **kwargs)
    start = make_scripted_labels(trajs, num_pairs=6, teacher=ReturnTeacher(), seed=1)
    assert labels.batch_size == (14,) and labels["teacher"] == "return"
    assert torch.equal(labels["index0"][:6], start["index0"])
    assert len(set(_pairs(labels))) == 14  # no pair asked twice
    ret = true_return(trajs)
    assert torch.equal(labels["label"], (ret[labels["index1"]] > ret[labels["index0"]]).float())
    again = make_query_labels(trajs, **kwargs)
    assert torch.equal(again["index0"], labels["index0"]) and torch.equal(again["index1"], labels["index1"])


def test_entropy_rounds_pick_pairs_the_model_finds_close(trajs):
    """The actively asked pairs are far closer in true return than uniform ones: the provisional
    model, which ranks the toy task well, spends the budget where the ranking is hard."""
    ret = true_return(trajs)
    labels = make_query_labels(trajs, num_pairs=30, teacher=ReturnTeacher(), seed=0, strategy="entropy",
                               initial=10, per_round=10, steps=150, model_kwargs=TINY_MODEL)
    uniform = make_scripted_labels(trajs, num_pairs=30, teacher=ReturnTeacher(), seed=0)

    def gap(lab):
        return (ret[lab["index1"][10:]] - ret[lab["index0"][10:]]).abs().median()

    assert gap(labels) < 0.5 * gap(uniform), (gap(labels), gap(uniform))


def test_all_ties_fall_back_to_uniform_rounds(trajs):
    class Indifferent(ReturnTeacher):
        def __call__(self, tau0, tau1):
            return torch.full(tau0.batch_size[:1], 0.5)

    labels = make_query_labels(trajs, num_pairs=10, teacher=Indifferent(), seed=0, strategy="entropy",
                               initial=4, per_round=3, steps=5, model_kwargs=TINY_MODEL)
    assert labels.batch_size == (10,) and len(set(_pairs(labels))) == 10
    assert bool((labels["label"] == 0.5).all())


def test_bad_query_options_are_clear_errors(trajs):
    base = dict(num_pairs=8, teacher=ReturnTeacher(), seed=0)
    with pytest.raises(ValueError, match="unknown strategy 'margin'"):
        make_query_labels(trajs, **base, strategy="margin")
    with pytest.raises(ValueError, match="members >= 2"):
        make_query_labels(trajs, **base, strategy="disagreement", members=1, initial=4)
    with pytest.raises(ValueError, match="initial >= 2"):
        make_query_labels(trajs, **base, strategy="entropy", initial=1)
    with pytest.raises(ValueError, match="only 190 distinct pairs"):
        make_query_labels(trajs, num_pairs=191, teacher=ReturnTeacher(), seed=0, strategy="entropy")


def test_bench_summary_marks_rows_taken_from_the_first_run(tmp_path):
    import json
    from pathlib import Path

    from torchrl_ftb.testing import load_script

    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "score_model_queries.py", "bench_queries")
    (tmp_path / "score_model_queries_nodistinct").mkdir()
    res = lambda *v: {"spearman_return": list(v), "mean": sum(v) / len(v)}  # noqa: E731
    (tmp_path / "score_model_queries_t.json").write_text(json.dumps({"results": {"entropy": res(0.9, 0.8)}}))
    (tmp_path / "score_model_queries_nodistinct" / "score_model_queries_t.json").write_text(
        json.dumps({"results": {"random": res(0.5, 0.7), "entropy": res(0.1, 0.1)}}))
    table = bench.summary(tmp_path)
    assert "| t | 0.6000* (0.50 / 0.70) | **0.8500** (0.90 / 0.80) | — |" in table


def test_bench_summary_adds_a_column_per_final_ensemble(tmp_path):
    import json
    from pathlib import Path

    from torchrl_ftb.testing import load_script

    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "score_model_queries.py", "bench_queries")
    assert bench.result_key("disagreement", 1) == "disagreement"
    assert bench.result_key("disagreement", 3) == "disagreement+ens3"
    assert bench.result_key("disagreement", 1, per_round=5) == "disagreement-r5"
    assert bench.result_key("disagreement", 3, per_round=5) == "disagreement-r5+ens3"
    assert bench.result_key("random", 1, per_round=5) == "random"
    assert bench.result_key("disagreement", 1, steps=1500, lr=1e-4) == "disagreement@s1500-lr0.0001"
    res = lambda *v: {"spearman_return": list(v), "mean": sum(v) / len(v)}  # noqa: E731
    (tmp_path / "score_model_queries_a.json").write_text(json.dumps({"results": {"random": res(0.5, 0.5)}}))
    (tmp_path / "score_model_queries_b.json").write_text(
        json.dumps({"results": {"random": res(0.7, 0.7), "disagreement+ens3": res(0.8, 0.9)}}))
    table = bench.summary(tmp_path).splitlines()
    assert table[0] == "| task | random (the paper) | entropy | disagreement | disagreement+ens3 |"
    assert table[2] == "| a | 0.5000 (0.50 / 0.50) | — | — | — |"
    assert table[3] == "| b | 0.7000 (0.70 / 0.70) | — | — | **0.8500** (0.80 / 0.90) |"


def test_bench_keeps_the_provenance_of_earlier_results(tmp_path):
    import json
    from pathlib import Path

    from torchrl_ftb.testing import load_script

    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "score_model_queries.py", "bench_queries")
    assert bench.earlier_results(tmp_path / "none.json") == {}
    path = tmp_path / "score_model_queries_t.json"
    path.write_text(json.dumps({"command": "old", "commit": "abc", "machine": {"cpu": "x"}, "results": {
        "entropy": {"mean": 0.5}, "disagreement": {"mean": 0.6, "command": "new", "commit": "def", "machine": {}}}}))
    results = bench.earlier_results(path)
    assert results["entropy"] == {"mean": 0.5, "command": "old", "commit": "abc", "machine": {"cpu": "x"}}
    assert results["disagreement"]["command"] == "new"
