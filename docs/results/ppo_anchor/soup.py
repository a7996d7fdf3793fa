"""Interpolate two checkpoints of the same network (WiSE-FT style weight averaging).

    python docs/results/ppo_anchor/soup.py BASE.zip TUNED.zip ALPHA OUT.zip

OUT holds BASE's archive with every floating-point tensor of ``policy.pth`` replaced by
``(1 - ALPHA) * base + ALPHA * tuned``; ALPHA 0 is BASE, 1 is TUNED's weights. The two
policies must have the same parameter names and shapes (a ValueError names the first that
differs). The archive is written to a temporary file next to OUT and then renamed.
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
import zipfile

import torch


def soup(base: str, tuned: str, alpha: float, out: str) -> None:
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"ALPHA must lie in [0, 1], got {alpha}")
    with zipfile.ZipFile(base) as zb, zipfile.ZipFile(tuned) as zt:
        sb = torch.load(io.BytesIO(zb.read("policy.pth")), map_location="cpu")
        st = torch.load(io.BytesIO(zt.read("policy.pth")), map_location="cpu")
        if sb.keys() != st.keys():
            raise ValueError(f"{tuned}: parameter names differ from {base}: "
                             f"{sorted(set(sb) ^ set(st))[:3]}")
        mixed = {}
        for name, tensor in sb.items():
            if tensor.shape != st[name].shape:
                raise ValueError(f"{tuned}: {name} has shape {tuple(st[name].shape)}, "
                                 f"{base} has {tuple(tensor.shape)}")
            mixed[name] = ((1.0 - alpha) * tensor + alpha * st[name]).to(tensor.dtype) \
                if tensor.is_floating_point() else tensor
    write_policy_archive(base, mixed, out)


def write_policy_archive(source: str, state: dict, out: str) -> None:
    """Write ``source``'s SB3 archive to ``out`` with ``policy.pth`` replaced by ``state``:
    to a temporary file next to OUT, then renamed (also used by ``condition_gain.py``)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    fd, tmp = tempfile.mkstemp(suffix=".zip", dir=os.path.dirname(os.path.abspath(out)))
    os.close(fd)
    try:
        with zipfile.ZipFile(source) as zs, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zo:
            for item in zs.infolist():
                zo.writestr(item, buf.getvalue() if item.filename == "policy.pth" else zs.read(item))
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    soup(sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4])
