"""Pure pieces of the CounterPlay search: backtracking, ranking, admission, verification.

Everything here is plain NumPy on small per-search arrays, so it can be tested on
hand-made data and reused by the batched branch runner in ``algorithm.py``.

Conventions (all steps are decision indices of the *same* episode, counted from its reset):

* ``values[t]``: the focal agent's critic value at decision ``t`` (float array, shape (T,)).
* ``root_steps``: the decisions at which a root (world snapshot + memories) was stored.
* ``failure_step``: the focal agent's last decision, the one whose outcome was a failure.
* Branch outcomes (:class:`BranchOutcome`) carry per-vehicle arrays of shape (A,) indexed
  by agent slot; ``-1`` means "never happened".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

__all__ = [
    "BACKTRACK_MODES",
    "SELECTION_MODES",
    "ROOT_LIFETIMES",
    "BranchOutcome",
    "select_root",
    "rank_key",
    "rank_branches",
    "ADMISSION_VERDICTS",
    "admission_verdict",
    "admit",
    "verify",
    "choose_teacher",
]

BACKTRACK_MODES: tuple[str, ...] = ("value", "fixed")
SELECTION_MODES: tuple[str, ...] = ("rank", "return")
#: How long a recorded root stays usable: while its world's episode runs ("episode"), or
#: only until the generation that recorded it ends ("generation").
ROOT_LIFETIMES: tuple[str, ...] = ("episode", "generation")


def _check_window(window: Sequence[int]) -> tuple[int, int]:
    if len(window) != 2:
        raise ValueError(f"window: expected (start, end), got {window!r}")
    start, end = int(window[0]), int(window[1])
    if start < 1:
        raise ValueError(f"window: start must be >= 1 decision before the failure, got {start}")
    if start >= end:
        raise ValueError(f"window: start must be < end, got {window!r}")
    return start, end


def select_root(
    values: np.ndarray | Sequence[float],
    root_steps: np.ndarray | Sequence[int],
    failure_step: int,
    window: Sequence[int] = (5, 60),
    rho: float = 0.5,
    mode: str = "value",
    fixed_depth: int | None = None,
) -> int | None:
    """Pick the decision step to backtrack to, or ``None`` when no root qualifies.

    ``mode="value"`` (the default, DESIGN.md): among roots ``r`` with
    ``window[0] <= failure_step - r <= window[1]``, let ``V_max`` be the highest focal
    critic value ``values[r]`` and ``V_f = values[failure_step]``; with
    ``V_thr = V_max - rho (V_max - V_f)``, return the latest root with
    ``values[r] >= V_thr``, else the earliest root in the window.

    ``mode="fixed"`` (ablation): the root nearest to ``failure_step - fixed_depth`` among
    the roots strictly before the failure (ties go to the earlier root); the window is
    not applied.

    Args:
        values: (T,) float, focal critic value per decision, ``T > failure_step``.
        root_steps: (R,) int, decisions that hold a root (any order, duplicates allowed).
        failure_step: the focal agent's last decision.
        window: (start, end) depth range in decisions, inclusive.
        rho: threshold position in [0, 1] between ``V_max`` (0) and ``V_f`` (1).
        mode: "value" or "fixed".
        fixed_depth: decisions before the failure for ``mode="fixed"`` (> 0).
    Returns:
        The chosen root's decision step (an element of ``root_steps``) or ``None``.
    """
    if mode not in BACKTRACK_MODES:
        raise ValueError(f"mode: expected one of {BACKTRACK_MODES}, got {mode!r}")
    roots = np.unique(np.asarray(root_steps, dtype=np.int64).reshape(-1))
    failure_step = int(failure_step)
    if mode == "fixed":
        if fixed_depth is None or int(fixed_depth) <= 0:
            raise ValueError(f"fixed_depth: must be a positive integer for mode='fixed', got {fixed_depth!r}")
        before = roots[(roots < failure_step) & (roots >= 0)]  # -1: no root (as in value mode)
        if before.size == 0:
            return None
        target = failure_step - int(fixed_depth)
        # np.unique sorts ascending, so argmin returns the earlier root on ties
        return int(before[np.argmin(np.abs(before - target))])

    if not 0.0 <= float(rho) <= 1.0:
        raise ValueError(f"rho: must lie in [0, 1], got {rho!r}")
    start, end = _check_window(window)
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if failure_step < 0 or failure_step >= values.shape[0]:
        raise ValueError(
            f"failure_step: {failure_step} outside the value trace of length {values.shape[0]}"
        )
    depth = failure_step - roots
    in_window = roots[(depth >= start) & (depth <= end) & (roots >= 0)]
    if in_window.size == 0:
        return None
    root_values = values[in_window]
    v_max = float(root_values.max())
    v_fail = float(values[failure_step])
    v_thr = v_max - float(rho) * (v_max - v_fail)
    good = in_window[root_values >= v_thr]
    if good.size:
        return int(good.max())   # latest qualifying root: closest to the failure
    return int(in_window.min())  # fallback: the earliest root of the window


@dataclass(frozen=True)
class BranchOutcome:
    """What one branch world produced for the ranking and admission tests.

    Attributes:
        focal: slot index of the focal agent.
        completed: the focal agent reached its goal before the deadline.
        arrival_step: decision at which the focal agent reached its goal (-1 if never).
        first_collision_step: (A,) int, first collision decision per slot (-1 none).
        first_offroad_step: (A,) int, first off-road decision per slot (-1 none).
        present: (A,) bool, slots holding a vehicle in this world (others are ignored).
        focal_return: the focal agent's conditioned return over the branch (for the
            ``selection="return"`` ablation).
    """

    focal: int
    completed: bool
    arrival_step: int
    first_collision_step: np.ndarray
    first_offroad_step: np.ndarray
    present: np.ndarray | None = None
    focal_return: float = 0.0
    others: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        col = np.asarray(self.first_collision_step, dtype=np.int64).reshape(-1)
        off = np.asarray(self.first_offroad_step, dtype=np.int64).reshape(-1)
        if col.shape != off.shape:
            raise ValueError(
                f"first_offroad_step: shape {off.shape} differs from first_collision_step {col.shape}"
            )
        present = np.ones(col.shape, bool) if self.present is None else np.asarray(self.present, bool).reshape(-1)
        if present.shape != col.shape:
            raise ValueError(f"present: shape {present.shape} differs from first_collision_step {col.shape}")
        if not 0 <= int(self.focal) < col.shape[0]:
            raise ValueError(f"focal: slot {self.focal} outside 0..{col.shape[0] - 1}")
        others = present.copy()
        others[int(self.focal)] = False
        object.__setattr__(self, "first_collision_step", col)
        object.__setattr__(self, "first_offroad_step", off)
        object.__setattr__(self, "present", present)
        object.__setattr__(self, "others", others)
        object.__setattr__(self, "completed", bool(self.completed))
        object.__setattr__(self, "arrival_step", int(self.arrival_step))

    @property
    def n_harmed(self) -> int:
        """Number of other vehicles that collide or go off-road in this branch."""
        harmed = (self.first_collision_step >= 0) | (self.first_offroad_step >= 0)
        return int(np.count_nonzero(harmed & self.others))

    @property
    def key(self) -> tuple[float, float, float]:
        """The rank key U(tau) of this branch (larger is better)."""
        return rank_key(self.completed, self.n_harmed, self.arrival_step)


def rank_key(completed: bool, n_harmed: int, arrival_step: int) -> tuple[float, float, float]:
    """U(tau) = (completed, -number of harmed other vehicles, -arrival time); larger is better.

    An incomplete branch has no arrival time: its last component is -inf, so it never
    wins on arrival.
    """
    arrival = -float(arrival_step) if completed and arrival_step >= 0 else -np.inf
    return (1.0 if completed else 0.0, -float(n_harmed), arrival)


def rank_branches(
    completed: Sequence[bool] | np.ndarray,
    n_harmed: Sequence[int] | np.ndarray,
    arrival_step: Sequence[int] | np.ndarray,
) -> np.ndarray:
    """Indices of the branches, best first by :func:`rank_key` (stable: ties keep order).

    All three arguments have shape (B,).
    """
    completed = np.asarray(completed, bool).reshape(-1)
    n_harmed = np.asarray(n_harmed, np.int64).reshape(-1)
    arrival_step = np.asarray(arrival_step, np.int64).reshape(-1)
    if not completed.shape == n_harmed.shape == arrival_step.shape:
        raise ValueError(
            "rank_branches: completed, n_harmed and arrival_step must have the same length, got "
            f"{completed.shape}, {n_harmed.shape}, {arrival_step.shape}"
        )
    keys = [rank_key(c, h, a) for c, h, a in zip(completed, n_harmed, arrival_step)]
    return np.array(sorted(range(len(keys)), key=lambda i: keys[i], reverse=True), dtype=np.int64)


def _check_pair(factual: BranchOutcome, candidate: BranchOutcome, argument: str) -> None:
    if factual.focal != candidate.focal:
        raise ValueError(f"{argument}: focal slot {candidate.focal} differs from factual {factual.focal}")
    if factual.first_collision_step.shape != candidate.first_collision_step.shape:
        raise ValueError(f"{argument}: number of slots differs from the factual branch")


def _no_new_or_earlier(factual_steps: np.ndarray, candidate_steps: np.ndarray, others: np.ndarray) -> bool:
    """Per vehicle: an event in the candidate needs the same event at the same or an earlier
    step in the factual branch."""
    happened = (candidate_steps >= 0) & others
    if not np.any(happened):
        return True
    f = factual_steps[happened]
    c = candidate_steps[happened]
    return bool(np.all((f >= 0) & (c >= f)))


#: What :func:`admission_verdict` can say about a retry, in the order its filters apply.
ADMISSION_VERDICTS: tuple[str, ...] = ("incomplete", "not_better", "harms_other", "admitted")


def admission_verdict(factual: BranchOutcome, candidate: BranchOutcome) -> str:
    """The first filter of :func:`admit` that ``candidate`` fails, or ``"admitted"``.

    ``"incomplete"``: it does not complete the task; ``"not_better"``: it completes but does
    not outrank ``factual`` (the factual branch completed too, and harmed fewer other vehicles,
    or as many and arrived no later: :func:`rank_key` compares harm before arrival);
    ``"harms_other"``: it completes and outranks, but some other vehicle gets a new
    or earlier collision / off-road. Counting these over a run shows which filter starves the
    search (:class:`cpalgo.counterplay.driver.SearchStats`, ``retries_*``).
    """
    _check_pair(factual, candidate, "candidate")
    if not candidate.completed:
        return "incomplete"
    if not candidate.key > factual.key:
        return "not_better"
    others = candidate.others | factual.others
    safe = _no_new_or_earlier(factual.first_collision_step, candidate.first_collision_step, others) and \
        _no_new_or_earlier(factual.first_offroad_step, candidate.first_offroad_step, others)
    return "admitted" if safe else "harms_other"


def admit(factual: BranchOutcome, candidate: BranchOutcome) -> bool:
    """Whether ``candidate`` may teach: it completes, outranks ``factual`` and causes no new
    or earlier collision / off-road for any other vehicle (per-vehicle test against the
    factual branch's first_collision_step / first_offroad_step)."""
    return admission_verdict(factual, candidate) == "admitted"


def verify(factual_rerun: BranchOutcome, candidate_rerun: BranchOutcome) -> bool:
    """Verification of a chosen teacher (the seed paper's): restore the root and rerun the
    factual and the chosen condition with fresh shared draws; the chosen condition's rerun
    must complete the task without a collision or off-road event of the focal agent, and
    pass the per-vehicle test against the new factual rerun (no other vehicle gets a new or
    earlier collision / off-road). It need *not* outrank the factual rerun: a lucky factual
    rerun that also completes does not fail verification. A ``False`` discards the whole
    search."""
    _check_pair(factual_rerun, candidate_rerun, "candidate_rerun")
    c = candidate_rerun
    if not c.completed:
        return False
    if c.first_collision_step[c.focal] >= 0 or c.first_offroad_step[c.focal] >= 0:
        return False
    others = c.others | factual_rerun.others
    return _no_new_or_earlier(factual_rerun.first_collision_step, c.first_collision_step, others) and \
        _no_new_or_earlier(factual_rerun.first_offroad_step, c.first_offroad_step, others)


def choose_teacher(
    factual: BranchOutcome,
    candidates: Sequence[BranchOutcome],
    selection: str = "rank",
) -> int | None:
    """Index of the teacher among ``candidates``, or ``None`` when there is none.

    ``selection="rank"``: the best admissible candidate (:func:`admit`) by :func:`rank_key`
    (ties: first in panel order); ``None`` when none is admissible.
    ``selection="return"`` (the selection-by-reward ablation): the candidate with the
    highest ``focal_return`` (its conditioned return under its own condition), with no
    completion, ranking or safety filter before it (ties: first in panel order); ``None``
    only when there is no candidate. Verification (:func:`verify`) still applies after
    either selection.
    """
    if selection not in SELECTION_MODES:
        raise ValueError(f"selection: expected one of {SELECTION_MODES}, got {selection!r}")
    if selection == "return":
        for c in candidates:
            _check_pair(factual, c, "candidate")
        if not candidates:
            return None
        returns = [float(c.focal_return) for c in candidates]
        returns = [-np.inf if np.isnan(r) else r for r in returns]  # a NaN return never wins
        return max(range(len(candidates)), key=lambda i: (returns[i], -i))
    admissible = [i for i, c in enumerate(candidates) if admit(factual, c)]
    if not admissible:
        return None
    return max(admissible, key=lambda i: (candidates[i].key, -i))
