"""cpalgo.counterplay.bench: the CounterPlay-vs-RecurrentPPO timing harness on a tiny setting."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("cpsim.simulator")
from cpalgo.counterplay import bench  # noqa: E402

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # run_benchmark sets torch's threads


def test_bench_reports_times_and_search_counts_per_generation(capsys):
    bench.main(["--worlds", "2", "--agents", "4", "--n-steps", "91", "--generations", "2", "--hidden", "16",
                "--branch-cap", "2.0"])
    result = json.loads(capsys.readouterr().out)
    assert result["recurrent_ppo_s_per_generation"] > 0 and result["counterplay_s_per_generation"] > 0
    assert len(result["recurrent_ppo_s_all"]) == len(result["counterplay_s_all"]) == 2
    verdicts = result["retry_verdicts_per_generation"]
    assert set(verdicts) == {"incomplete", "not_better", "harms_other", "admitted"}
    assert result["searches_per_generation"] > 0  # a fresh policy fails plenty of 91-step tasks
    # five retries per search
    assert sum(verdicts.values()) == pytest.approx(5 * result["searches_per_generation"])
    assert result["budget"]["generations"] >= 2


def test_bench_rejects_bad_arguments():
    with pytest.raises(SystemExit):
        bench.main(["--worlds", "0"])
    with pytest.raises(SystemExit):
        bench.main(["--branch-cap", "0"])
