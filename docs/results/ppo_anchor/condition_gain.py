"""Amplify a flat policy's response to the style fields of its condition around one profile.

    python docs/results/ppo_anchor/condition_gain.py MODEL.zip GAIN OUT.zip [--center normal] [--critic]

The first layer that reads the observation (``lstm_actor.weight_ih_l0``, shape (4H, D), and
with ``--critic`` also ``critic.weight``, (H, D)) sees the normalised condition c (10 fields,
:func:`cpsim.conditions.normalize_condition`) through its condition columns W_c. OUT holds
MODEL's archive with, for the style columns only (:data:`cpsim.conditions.STYLE_MASK`),

    W_c' = GAIN * W_c,    b' = b + (1 - GAIN) * W_c c_center

so that the layer's output at any observation whose style equals the ``--center`` profile is
unchanged (the policy under that deployment condition is the same function), and a style s
acts as the style ``c_center + GAIN (s - c_center)`` did before. Task fields (goal radius and
speed) keep their columns. GAIN 1 returns MODEL's weights. The archive is written to a
temporary file next to OUT and then renamed.
"""

from __future__ import annotations

import argparse
import io
import zipfile

import numpy as np
import torch
from soup import write_policy_archive  # this folder (the script's own directory is on sys.path)

from cpsim.conditions import PROFILES, STYLE_MASK, normalize_condition
from cpsim.observation import ObsLayout


def condition_gain(model: str, gain: float, out: str, center: str = "normal", critic: bool = False) -> None:
    if not np.isfinite(gain) or gain <= 0.0:
        raise ValueError(f"GAIN must be a positive number, got {gain}")
    if center not in PROFILES:
        raise ValueError(f"--center: unknown profile {center!r}; known: {sorted(PROFILES)}")
    layers = [("lstm_actor.weight_ih_l0", "lstm_actor.bias_ih_l0")]
    if critic:
        layers.append(("critic.weight", "critic.bias"))
    with zipfile.ZipFile(model) as zm:
        state = torch.load(io.BytesIO(zm.read("policy.pth")), map_location="cpu")
        cols = np.arange(ObsLayout().condition.start, ObsLayout().condition.stop)[STYLE_MASK]
        c_center = torch.as_tensor(normalize_condition(PROFILES[center])[STYLE_MASK])
        for w_name, b_name in layers:
            if w_name not in state or b_name not in state:
                raise ValueError(f"{model}: no {w_name} / {b_name}; the gain applies to the flat "
                                 "network (MlpLstmPolicy on the raw observation) only")
            w, b = state[w_name], state[b_name]
            if w.shape[1] != ObsLayout().size:
                raise ValueError(f"{model}: {w_name} reads {w.shape[1]} inputs, the observation "
                                 f"has {ObsLayout().size}")
            w_c = w[:, cols].clone()
            state[b_name] = b + (1.0 - gain) * (w_c @ c_center.to(w.dtype))
            w[:, cols] = gain * w_c
    write_policy_archive(model, state, out)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("gain", type=float)
    parser.add_argument("out")
    parser.add_argument("--center", default="normal")
    parser.add_argument("--critic", action="store_true")
    args = parser.parse_args()
    condition_gain(args.model, args.gain, args.out, args.center, args.critic)
