"""Per-agent reward conditions (GigaFlow / BehaviorBench style).

A condition is a vector of :data:`NUM_CONDITION_FIELDS` = 10 floats in raw units,
ordered as :data:`CONDITION_FIELDS`. Policies and critics see it normalised to
[-1, 1] over the training ranges (:func:`normalize_condition`).

The named driving styles are importable constants in :data:`PROFILES`; the
CounterPlay panel (cautious -> aggressive) is :data:`PANEL`.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

CONDITION_FIELDS: tuple[str, ...] = (
    "goal_radius",   # m
    "goal_speed",    # m/s, maximum speed at which reaching the goal counts
    "collision",     # penalty weight
    "offroad",       # penalty weight
    "comfort",       # penalty weight per comfort violation
    "lane_align",    # weight of the lane-alignment term
    "vel_align",     # weight of the velocity-alignment term
    "lane_center",   # weight of the lane-centring term
    "center_bias",   # lateral bias of the lane-centring target, m, positive keeps right (-0.5 .. 0.5)
    "reverse",       # penalty weight for reversing
)
NUM_CONDITION_FIELDS = len(CONDITION_FIELDS)
FIELD_INDEX: dict[str, int] = {name: i for i, name in enumerate(CONDITION_FIELDS)}

#: Fields that define the task (goal test) rather than the driving style. Retries of
#: CounterPlay change style fields only; these stay as they were.
TASK_FIELDS: tuple[str, ...] = ("goal_radius", "goal_speed")
STYLE_FIELDS: tuple[str, ...] = tuple(f for f in CONDITION_FIELDS if f not in TASK_FIELDS)
STYLE_MASK = np.array([f in STYLE_FIELDS for f in CONDITION_FIELDS])

#: p_train: independent uniform ranges (low, high) per field, in raw units.
TRAIN_LOW = np.array([2.0, 3.0, 0.0, 0.0, 0.0, 2.5e-4, 0.0, 2.5e-4, -0.5, 2.5e-4], np.float32)
TRAIN_HIGH = np.array([12.0, 30.0, 3.0, 3.0, 0.1, 2.5e-2, 1.0, 7.5e-3, 0.5, 7.5e-3], np.float32)


def _profile(**kw: float) -> np.ndarray:
    return np.array([kw[f] for f in CONDITION_FIELDS], np.float32)


_AGGRESSIVE = _profile(goal_radius=2.0, goal_speed=30.0, collision=0.2, offroad=0.2, comfort=0.0,
                       lane_align=0.001, vel_align=0.1, lane_center=0.00025, center_bias=0.0,
                       reverse=0.0005)
_NORMAL = _profile(goal_radius=2.0, goal_speed=20.0, collision=3.0, offroad=3.0, comfort=0.05,
                   lane_align=0.015, vel_align=0.5, lane_center=0.0038, center_bias=0.0,
                   reverse=0.0038)
_CAUTIOUS = _profile(goal_radius=2.0, goal_speed=5.0, collision=3.0, offroad=3.0, comfort=0.1,
                     lane_align=0.025, vel_align=1.0, lane_center=0.0075, center_bias=0.5,
                     reverse=0.0075)

#: Named profiles (raw units, read-only). Midpoints are field-wise means of adjacent styles.
PROFILES: Mapping[str, np.ndarray] = {
    "cautious": _CAUTIOUS,
    "cautious-normal": (0.5 * (_CAUTIOUS + _NORMAL)).astype(np.float32),
    "normal": _NORMAL,
    "normal-aggressive": (0.5 * (_NORMAL + _AGGRESSIVE)).astype(np.float32),
    "aggressive": _AGGRESSIVE,
}
for _v in PROFILES.values():
    _v.setflags(write=False)
# "halfway" is the name the evaluation CLI accepts for the normal/aggressive midpoint.
PROFILE_ALIASES: Mapping[str, str] = {"halfway": "normal-aggressive", "mid": "normal-aggressive"}

#: The CounterPlay panel of candidate styles, cautious to aggressive.
PANEL: tuple[str, ...] = ("cautious", "cautious-normal", "normal", "normal-aggressive", "aggressive")


def profile(name: str) -> np.ndarray:
    """Return a copy of the named profile's raw condition vector (10,) float32."""
    key = PROFILE_ALIASES.get(name, name)
    if key not in PROFILES:
        raise ValueError(
            f"unknown profile {name!r}; accepted: {sorted(PROFILES) + sorted(PROFILE_ALIASES)}"
        )
    return PROFILES[key].copy()


def with_panel_styles(conditions: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Raw conditions (..., 10) float32 whose style fields are those of the panel profile
    ``PANEL[index]`` (index: int array of the leading shape), task fields kept."""
    styles = np.stack([PROFILES[name] for name in PANEL])[np.asarray(index)]
    return np.where(STYLE_MASK, styles, np.asarray(conditions)).astype(np.float32)


def validate_conditions(conditions: np.ndarray, argument: str = "conditions") -> np.ndarray:
    """Check a (..., 10) array of raw conditions against the training ranges.

    Returns it as float32. Raises ``ValueError`` naming the argument and the field.
    """
    c = np.asarray(conditions, dtype=np.float32)
    if c.ndim < 1 or c.shape[-1] != NUM_CONDITION_FIELDS:
        raise ValueError(f"{argument}: last dimension must be {NUM_CONDITION_FIELDS}, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{argument}: contains NaN or infinite values")
    tol = 1e-6
    low_bad = c < TRAIN_LOW - tol * np.maximum(1.0, np.abs(TRAIN_LOW))
    high_bad = c > TRAIN_HIGH + tol * np.maximum(1.0, np.abs(TRAIN_HIGH))
    bad = np.any((low_bad | high_bad).reshape(-1, NUM_CONDITION_FIELDS), axis=0)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(
            f"{argument}: field '{CONDITION_FIELDS[i]}' outside its range "
            f"[{TRAIN_LOW[i]:g}, {TRAIN_HIGH[i]:g}]"
        )
    return c


def sample_conditions(rng: np.random.Generator, shape: Sequence[int] | int) -> np.ndarray:
    """Draw raw conditions from p_train: array of shape (*shape, 10) float32."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    u = rng.random((*shape, NUM_CONDITION_FIELDS), dtype=np.float32)
    return (TRAIN_LOW + u * (TRAIN_HIGH - TRAIN_LOW)).astype(np.float32)


def normalize_condition(conditions: np.ndarray) -> np.ndarray:
    """Map raw (..., 10) conditions to [-1, 1] over the p_train ranges (NumPy or torch)."""
    low = TRAIN_LOW
    span = TRAIN_HIGH - TRAIN_LOW
    if hasattr(conditions, "new_tensor"):  # torch tensor: keep device and dtype
        low = conditions.new_tensor(low)
        span = conditions.new_tensor(span)
    return 2.0 * (conditions - low) / span - 1.0


def criterion_task_fields() -> np.ndarray:
    """The task fields (goal_radius, goal_speed) a policy sees under the evaluation goal
    criterion (:data:`cpsim.config.EVAL_GOAL`): its radius and speed clipped to p_train's
    ranges, (2 m, 30 m/s). The simulator tests the goal with the criterion itself (2 m,
    100 m/s); with jerk dynamics (speed <= 20 m/s) any goal speed >= 20 is no limit, so the
    two agree."""
    from cpsim.config import EVAL_GOAL

    idx = [FIELD_INDEX[f] for f in TASK_FIELDS]
    raw = np.array([EVAL_GOAL.radius, EVAL_GOAL.speed], np.float32)
    return np.clip(raw, TRAIN_LOW[idx], TRAIN_HIGH[idx]).astype(np.float32)


def with_eval_task(rng: np.random.Generator, conditions: np.ndarray, share: float) -> np.ndarray:
    """Give a random ``share`` of the agents the evaluation criterion's task fields, in place.

    Args:
        conditions: (..., 10) raw conditions, modified in place and returned.
        share: probability per agent, in [0, 1]; one ``rng.random(conditions.shape[:-1])``
            draw decides.
    """
    idx = [FIELD_INDEX[f] for f in TASK_FIELDS]
    pick = rng.random(conditions.shape[:-1]) < share
    conditions[..., idx] = np.where(pick[..., None], criterion_task_fields(), conditions[..., idx])
    return conditions


def with_panel_share(rng: np.random.Generator, conditions: np.ndarray, share: float) -> np.ndarray:
    """Give a random ``share`` of the agents the style fields of a random panel profile.

    Oversamples the panel's five styles (:data:`PANEL`) among p_train draws, so that a
    policy trains on the exact profiles it is deployed and searched under. Task fields stay.

    Args:
        conditions: (..., 10) raw conditions; not modified.
        share: probability per agent, in [0, 1].

    Returns:
        (..., 10) float32: a new array. Two draws of ``rng`` decide, in this order: the
        profile index of every agent, then whether it takes it.
    """
    shape = conditions.shape[:-1]
    index = rng.integers(0, len(PANEL), size=shape)
    pick = rng.random(shape) < share
    styled = with_panel_styles(conditions, index)
    return np.where(pick[..., None], styled, conditions).astype(np.float32)


def deployment_condition(spec: str | Sequence[float] | np.ndarray, argument: str = "condition") -> np.ndarray:
    """The raw (10,) condition of a deployed agent: the style fields of ``spec`` (a profile
    name or a raw 10-vector) and the task fields of the evaluation goal criterion
    (:func:`criterion_task_fields`). A deployment condition changes style fields only: the
    goal test is the same whatever the profile (DESIGN.md, "Evaluation goal criterion")."""
    cond = resolve_condition(spec, argument).copy()
    cond[~STYLE_MASK] = criterion_task_fields()
    return cond


def resolve_condition(spec: str | Sequence[float] | np.ndarray, argument: str = "condition") -> np.ndarray:
    """Turn a profile name or an explicit 10-vector into a validated raw (10,) condition."""
    if isinstance(spec, str):
        try:
            return profile(spec)
        except ValueError as exc:
            raise ValueError(f"{argument}: {exc}") from None
    vec = np.asarray(spec, np.float32)
    if vec.shape != (NUM_CONDITION_FIELDS,):
        raise ValueError(
            f"{argument}: expected a profile name {sorted(PROFILES)} or a vector of "
            f"{NUM_CONDITION_FIELDS} values {CONDITION_FIELDS}, got shape {vec.shape}"
        )
    return validate_conditions(vec, argument)
