"""cpalgo.bench: the learn-throughput benchmark (stock / fused / ppo / counterplay) on a tiny setting."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("cpsim.simulator")
import torch  # noqa: E402

from cpalgo import bench  # noqa: E402

pytestmark = pytest.mark.usefixtures("_one_torch_thread")  # run_learn_benchmark may set torch's threads


def _has_cuda() -> bool:
    import warp as wp

    wp.init()
    return torch.cuda.is_available() and wp.get_cuda_device_count() > 0


def test_learn_benchmark_times_every_learner_on_the_shipped_network(tmp_path, capsys):
    out = tmp_path / "bench.json"
    bench.main(["--worlds", "1", "--agents", "4", "--n-steps", "8", "--batch-size", "16", "--epochs", "1",
                "--generations", "1", "--learners", "stock,ppo,counterplay", "--out", str(out)])
    result = json.loads(out.read_text())
    assert json.loads(capsys.readouterr().out) == result
    assert result["slots"] == 4 and result["device"] == "cpu" and "lstm_hidden_size" in result["network"]
    for name in ("stock", "ppo", "counterplay"):
        entry = result["learners"][name]
        assert entry["s_per_generation"] > 0 and entry["slot_steps_per_s"] == pytest.approx(32 / entry["s_per_generation"])
        assert entry["train_s"] > 0
    assert result["speedup_vs_stock"]["stock"] == pytest.approx(1.0)


def test_learn_benchmark_rejects_a_device_it_cannot_use():
    with pytest.raises(ValueError, match="device: expected 'cpu' or 'cuda"):
        bench.run_learn_benchmark(worlds=1, agents=2, device="tpu")
    if not _has_cuda():
        with pytest.raises(ValueError, match="no CUDA device"):
            bench.run_learn_benchmark(worlds=1, agents=2, device="cuda")


@pytest.mark.cuda
def test_learn_benchmark_runs_on_the_gpu():
    if not _has_cuda():
        pytest.skip("needs a CUDA device (Warp and torch)")
    result = bench.run_learn_benchmark(worlds=2, agents=4, n_steps=8, generations=1, batch_size=16, n_epochs=1,
                                       learners=("ppo", "counterplay"), device="cuda")
    assert result["device"] == "cuda" and all(e["s_per_generation"] > 0 for e in result["learners"].values())


RECIPE = """cpsim/SelfPlay-v0:
  policy: '{policy}'
  n_envs: 8
  n_timesteps: 100
  n_steps: 8
  batch_size: 32
  n_epochs: {epochs}
  policy_kwargs: "{kwargs}"
  env_kwargs:
    max_agents: 4
    dynamics: {dynamics}
"""


def test_recipe_benchmark_times_whole_recipes_and_counts_their_flops(tmp_path, capsys):
    behavior = tmp_path / "behavior.yml"
    behavior.write_text(RECIPE.format(policy="BehaviorLstmPolicy", epochs=1, dynamics="classic",
                                      kwargs="dict(lstm_hidden_size=16)"))
    flat = tmp_path / "flat.yml"
    flat.write_text(RECIPE.format(policy="MlpLstmPolicy", epochs=2, dynamics="jerk",
                                  kwargs="dict(lstm_hidden_size=16, net_arch=dict(pi=[16], vf=[16]))"))
    bench.main(["--recipes", f"{flat},{behavior}", "--generations", "1", "--out", str(tmp_path / "r.json")])
    result = json.loads((tmp_path / "r.json").read_text())
    assert json.loads(capsys.readouterr().out) == result
    a, b = result["recipes"][str(flat)], result["recipes"][str(behavior)]
    assert a["policy"] == "MlpLstmPolicy" and b["policy"] == "BehaviorLstmPolicy" and a["n_epochs"] == 2
    for entry in (a, b):
        assert entry["live_transitions_per_s"] == pytest.approx(entry["live_transitions_per_generation"]
                                                                / entry["s_per_generation"])
        f = entry["flops_per_transition"]
        assert f["train"] > 2 * f["inference"] > 0
        assert f["total"] == pytest.approx(f["inference"] + entry["n_epochs"] * f["train"])
    # the flat network feeds the 699-wide observation into its LSTM (16 hidden): counted analytically
    assert a["flops_per_transition"]["inference"] >= 2 * 4 * 16 * (699 + 16)
    assert result["speedup_vs_first"][str(flat)] == pytest.approx(1.0)
