"""Data-parallel PPO over a ``torch.distributed`` process group (gloo, CPU).

Every rank runs the same algorithm on its own envs; the ranks agree on what the update
needs to stay in step (:func:`cpalgo.common.ppo_update.run_update`): the gradient of every
optimizer step is averaged over the ranks that had data for it, the minibatch count of an
epoch is the largest of any rank, early stopping sees the ranks' mean KL. With averaged
gradients, identical starting parameters and identical optimizer states, every rank keeps
identical parameters without further communication.

The transition count (``num_timesteps``, which drives the schedules and ``learn``'s stop)
is summed over the ranks at each rollout's end by
:meth:`cpalgo.counterplay.algorithm.CounterPlay.collect_rollouts`; the self-play anchor
trainer (:mod:`cpalgo.anchor.selfplay`, ``--workers``) starts and runs the ranks.

Without an initialised process group (or with one rank) every function here is the
identity of one process: :func:`data_parallel` is False and the callers take their
single-process path unchanged.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch as th

__all__ = ["data_parallel", "rank", "world_size", "all_reduce_sum", "agree_max", "joint_mean",
           "average_gradients", "broadcast_parameters", "broadcast_object", "gather_objects"]


def _initialized() -> bool:
    return bool(th.distributed.is_available() and th.distributed.is_initialized())


def world_size() -> int:
    """Ranks of the process group (1 without one)."""
    return th.distributed.get_world_size() if _initialized() else 1


def rank() -> int:
    """This process's rank (0 without a process group)."""
    return th.distributed.get_rank() if _initialized() else 0


def data_parallel() -> bool:
    """Whether a process group of more than one rank is initialised."""
    return world_size() > 1


def all_reduce_sum(values: Any) -> np.ndarray:
    """Elementwise sum over the ranks of ``values`` (a number or an array, any shape),
    as float64 (exact for counts below 2**53)."""
    local = np.asarray(values, dtype=np.float64)
    if not data_parallel():
        return local.copy()
    tensor = th.as_tensor(local.reshape(-1).copy())
    th.distributed.all_reduce(tensor, op=th.distributed.ReduceOp.SUM)
    return tensor.numpy().reshape(local.shape)


def agree_max(value: int) -> int:
    """The largest ``value`` of any rank."""
    if not data_parallel():
        return int(value)
    tensor = th.tensor([int(value)], dtype=th.int64)
    th.distributed.all_reduce(tensor, op=th.distributed.ReduceOp.MAX)
    return int(tensor.item())


def joint_mean(value: float | None) -> float:
    """Mean of ``value`` over the ranks that give one (None: this rank has none); NaN when
    no rank has one."""
    total, count = all_reduce_sum([0.0 if value is None else float(value), 0.0 if value is None else 1.0])
    return float(total / count) if count > 0 else float("nan")


def average_gradients(parameters: Iterable[th.nn.Parameter], contributes: bool) -> bool:
    """Replace every parameter's ``.grad`` by its mean over the ranks that contribute.

    One flattened float32 buffer is all-reduced: the gradients (a parameter without one
    counts as zeros), one has-a-gradient flag per parameter and the contribution flag. A
    rank that does not contribute (its minibatch holds no live transition) adds zeros, so
    the mean is the one of the ranks that had data, and it still takes the step the others
    take: every rank keeps the same optimizer-step count.

    Args:
        parameters: the optimised parameters, in the same order on every rank.
        contributes: whether this rank's ``.grad`` values hold a gradient of this step.
    Returns:
        Whether any rank contributed (False: no rank had data; the grads are left None and
        the callers skip the step on every rank alike).
    """
    params = list(parameters)
    pieces: list[th.Tensor] = []
    for p in params:
        if contributes and p.grad is not None:
            pieces.append(p.grad.detach().reshape(-1).to(th.float32))
        else:
            pieces.append(th.zeros(p.numel(), dtype=th.float32, device=p.device))
    has_grad = [1.0 if contributes and p.grad is not None else 0.0 for p in params]
    flags = th.tensor([*has_grad, 1.0 if contributes else 0.0], dtype=th.float32)
    flat = th.cat([*pieces, flags.to(pieces[0].device if pieces else "cpu")])
    th.distributed.all_reduce(flat, op=th.distributed.ReduceOp.SUM)
    contributors = float(flat[-1].item())
    if contributors <= 0:
        for p in params:
            p.grad = None
        return False
    offset = 0
    for p, seen in zip(params, flat[flat.numel() - 1 - len(params):-1].tolist()):
        n = p.numel()
        if seen > 0:
            # the mean over the ranks that had data (the others added zeros)
            p.grad = (flat[offset:offset + n] / contributors).view_as(p).to(p.dtype)
        else:
            p.grad = None  # no rank computed one: the optimizer skips it, as in one process
        offset += n
    return True


def broadcast_parameters(module: th.nn.Module, src: int = 0) -> None:
    """Copy rank ``src``'s parameters and buffers into every rank's ``module`` (in place)."""
    if not data_parallel():
        return
    with th.no_grad():
        for tensor in [*module.parameters(), *module.buffers()]:
            th.distributed.broadcast(tensor.data, src=src)


def broadcast_object(obj: Any, src: int = 0) -> Any:
    """Rank ``src``'s picklable ``obj`` on every rank (``obj`` on the others is ignored)."""
    if not data_parallel():
        return obj
    box = [obj if rank() == src else None]
    th.distributed.broadcast_object_list(box, src=src)
    return box[0]


def gather_objects(obj: Any) -> list[Any]:
    """Every rank's picklable ``obj``, in rank order, on every rank (``[obj]`` alone)."""
    if not data_parallel():
        return [obj]
    out: list[Any] = [None] * world_size()
    th.distributed.all_gather_object(out, obj)
    return out
