"""Write a copy of a checkpoint whose action distribution has temperature ``T``.

The actor's logits are divided by ``T`` by scaling the action head (``policy.action_net``,
weight and bias) by ``1 / T``. Nothing else changes: the critic, the LSTMs and the condition
inputs are the same tensors, and the argmax action of every observation is unchanged, so every
deterministic evaluation (``cpalgo.evaluate``, argmax traffic) gives bit-identical results.
What changes is every sampled decision: self-play rollouts, CounterPlay's branches and
verification, and PPO's starting point.

    python docs/results/temperature/sharpen.py zoo/anchor.zip 0.5 runs/temperature/J16_T05.zip
"""

from __future__ import annotations

import argparse

import torch as th

from cpalgo.checkpoint import save_model_atomic
from cpalgo.evaluate.runner import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("temperature", type=float)
    parser.add_argument("out")
    args = parser.parse_args()
    if not 0.0 < args.temperature <= 1.0:
        raise SystemExit(f"temperature: expected 0 < T <= 1, got {args.temperature}")
    model = load_model(args.model, "model")
    head = model.policy.action_net
    with th.no_grad():
        head.weight.mul_(1.0 / args.temperature)
        head.bias.mul_(1.0 / args.temperature)
    out = save_model_atomic(model, args.out)
    print(f"{args.model} -> {out}: action logits / {args.temperature}")


if __name__ == "__main__":
    main()
