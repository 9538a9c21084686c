"""Shared pytest set-up: deterministic, CPU-friendly, headless."""
import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="module")
def one_thread():
    """Small models on a shared 2-core machine: one intra-op thread beats two oversubscribed ones.

    Use per module with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def toy_data():
    from torchrl_ftb.testing import make_toy_dataset

    return make_toy_dataset(num_trajectories=64, horizon=16, seed=0)


@pytest.fixture
def report_rows():
    """``rows(recipe, analysis=..., env=...)``: the recipe's final table (``{metric: value}``) of a minimal finished
    run's metrics, with ``analysis`` as its ``metrics["analysis"]`` (the report-row tests of each analysis)."""

    def rows(recipe, *, analysis: dict, env: str = "button-press-v3") -> dict[str, str]:
        metrics = {"env": env, "preset": "cpu", "teacher": "return", "wall_time_s": 1.0,
                   "eval": {"return_mean": 0.0, "return_std": 0.0, "length_mean": 1.0},
                   "flow": {"score_mean_before": 0.0, "score_mean_after": 1.0, "flow_steps_run": 1,
                            "flow_steps_planned": 1, "fraction_generated_in_final": 0.5},
                   "score_quality": {}, "analysis": analysis}
        return dict(recipe.final_table(metrics))

    return rows
