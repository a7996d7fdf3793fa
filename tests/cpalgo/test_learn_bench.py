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
