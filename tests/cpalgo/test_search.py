"""Root selection, ranking, admission and verification on hand-made data."""

from __future__ import annotations

import numpy as np
import pytest

from cpalgo.counterplay.search import (
    ADMISSION_VERDICTS,
    BranchOutcome,
    admission_verdict,
    admit,
    choose_teacher,
    rank_branches,
    rank_key,
    select_root,
    verify,
)

# ----------------------------------------------------------------------------- select_root


def _trace(points: dict[int, float], length: int = 91, fill: float = 0.0) -> np.ndarray:
    v = np.full(length, fill)
    for t, x in points.items():
        v[t] = x
    return v


def test_select_root_latest_root_above_threshold():
    # failure at 70; window 5..60 -> roots 10..65. V_max = 4 at root 20, V_f = 0 at 70,
    # threshold = 2: roots with V >= 2 are 20 (4.0), 35 (2.5), 40 (2.0); latest is 40.
    values = _trace({10: 1.0, 15: 1.5, 20: 4.0, 25: 1.0, 30: 1.9, 35: 2.5, 40: 2.0, 45: 1.0,
                     50: 0.5, 55: 0.1, 60: -1.0, 65: -2.0, 70: 0.0})
    roots = np.arange(0, 91, 5)
    assert select_root(values, roots, failure_step=70) == 40


def test_select_root_threshold_moves_with_rho():
    values = _trace({10: 1.0, 20: 4.0, 30: 3.1, 40: 2.0, 50: 1.0, 70: 0.0})
    roots = [10, 20, 30, 40, 50]
    # rho = 0 -> threshold = V_max -> only the maximum qualifies
    assert select_root(values, roots, 70, rho=0.0) == 20
    # rho = 0.2 -> threshold 3.2: still only root 20 (3.1 < 3.2)
    assert select_root(values, roots, 70, rho=0.2) == 20
    # rho = 0.25 -> threshold 3.0: root 30 qualifies and is later
    assert select_root(values, roots, 70, rho=0.25) == 30
    # rho = 1 -> threshold V_f = 0: every root qualifies, the latest wins
    assert select_root(values, roots, 70, rho=1.0) == 50


def test_select_root_window_excludes_too_close_and_too_far_roots():
    values = _trace({0: 100.0, 68: 50.0, 20: 1.0, 40: 2.0, 70: 0.0})
    # root 0 is 70 decisions back (> 60), root 68 only 2 back (< 5): both ignored
    assert select_root(values, [0, 20, 40, 68], 70) == 40
    # inclusive bounds: depth exactly 5 and exactly 60 are in the window
    assert select_root(_trace({10: 1.0, 65: 1.0, 70: 0.0}), [10, 65], 70) == 65
    assert select_root(_trace({10: 1.0, 70: 0.0}), [10], 70) == 10


def test_select_root_fallback_to_earliest_when_failure_value_is_highest():
    # V_f above every root value: V_thr > V_max, nothing qualifies -> earliest in window
    values = _trace({20: 1.0, 30: 2.0, 40: 1.5, 70: 5.0})
    assert select_root(values, [5, 20, 30, 40], 70) == 20


def test_select_root_ignores_negative_root_steps():
    # a negative step is no decision of this episode: root -5 would be 25 decisions before
    # the failure at 20 (inside the window) and would read values[-5], i.e. values[86] = 9
    values = _trace({15: 1.0, 20: 0.0, 86: 9.0})
    assert select_root(values, [-5, 15], 20) == 15
    assert select_root(values, [-5], 20) is None
    # the fixed-depth ablation ignores them too: -1 would be nearest to 70 - 80 = -10
    assert select_root(np.zeros(91), [-1, 30], 70, mode="fixed", fixed_depth=80) == 30
    assert select_root(np.zeros(91), [-1], 70, mode="fixed", fixed_depth=80) is None


def test_select_root_empty_window_returns_none():
    values = _trace({3: 1.0, 70: 0.0})
    assert select_root(values, [], 70) is None
    assert select_root(values, [68, 69], 70) is None
    assert select_root(values, [3], 4) is None


def test_select_root_fixed_depth_nearest_available():
    values = np.zeros(91)
    roots = np.arange(0, 91, 5)
    assert select_root(values, roots, 70, mode="fixed", fixed_depth=20) == 50
    # target 47 -> nearest root 45
    assert select_root(values, roots, 67, mode="fixed", fixed_depth=20) == 45
    # target 47.5 impossible; target 45+2.5 ties are broken to the earlier root
    assert select_root(values, [40, 50], 65, mode="fixed", fixed_depth=20) == 40
    # only roots before the failure count
    assert select_root(values, [70, 75], 70, mode="fixed", fixed_depth=20) is None
    # deeper than the available history: earliest root
    assert select_root(values, [30, 60], 70, mode="fixed", fixed_depth=80) == 30


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"window": (60, 5)}, "window"),
        ({"window": (5, 5)}, "window"),
        ({"rho": 1.5}, "rho"),
        ({"rho": -0.1}, "rho"),
        ({"mode": "random"}, "mode"),
        ({"mode": "fixed"}, "fixed_depth"),
        ({"mode": "fixed", "fixed_depth": 0}, "fixed_depth"),
    ],
)
def test_select_root_rejects_bad_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        select_root(np.zeros(91), [10, 20], 70, **kwargs)


def test_select_root_rejects_failure_outside_trace():
    with pytest.raises(ValueError, match="failure_step"):
        select_root(np.zeros(10), [1, 2], 20)


# ----------------------------------------------------------------------------- ranking


def _outcome(completed, arrival=-1, col=None, off=None, focal=0, ret=0.0, n=4):
    col = np.full(n, -1) if col is None else np.asarray(col)
    off = np.full(n, -1) if off is None else np.asarray(off)
    return BranchOutcome(focal=focal, completed=completed, arrival_step=arrival,
                         first_collision_step=col, first_offroad_step=off, focal_return=ret)


def test_rank_key_orders_completion_then_harm_then_arrival():
    assert rank_key(True, 3, 90) > rank_key(False, 0, -1)
    assert rank_key(True, 0, 90) > rank_key(True, 1, 10)
    assert rank_key(True, 1, 40) > rank_key(True, 1, 41)
    assert rank_key(False, 0, -1) > rank_key(False, 2, -1)


def test_rank_key_ignores_the_arrival_of_an_incomplete_branch():
    # an incomplete branch has no arrival time, even when a stale step is passed along
    assert rank_key(False, 0, 30) == rank_key(False, 0, -1) == (0.0, 0.0, -np.inf)
    assert rank_key(True, 0, -1)[2] == -np.inf
    # so among incomplete branches a stale arrival step does not reorder them (stable)
    assert rank_branches([False, False], [0, 0], [-1, 30]).tolist() == [0, 1]


def test_rank_branches_best_first_and_stable():
    order = rank_branches(
        completed=[False, True, True, True, True],
        n_harmed=[0, 1, 0, 0, 0],
        arrival_step=[-1, 30, 50, 40, 40],
    )
    assert order.tolist() == [3, 4, 2, 1, 0]


def test_n_harmed_ignores_focal_and_absent_slots():
    o = BranchOutcome(focal=1, completed=True, arrival_step=50,
                      first_collision_step=[-1, 20, 30, -1], first_offroad_step=[10, -1, -1, 5],
                      present=[True, True, True, False])
    # slot 1 is the focal, slot 3 is absent: harmed = slot 0 (off-road) and slot 2 (collision)
    assert o.n_harmed == 2


# ----------------------------------------------------------------------------- admission


def test_admit_accepts_completing_harmless_candidate():
    factual = _outcome(False)
    cand = _outcome(True, arrival=60)
    assert admit(factual, cand)


def test_admit_rejects_incomplete_or_not_better():
    assert not admit(_outcome(False), _outcome(False))
    # factual also completes, earlier: the candidate does not outrank it
    assert not admit(_outcome(True, arrival=40), _outcome(True, arrival=50))
    # same rank key: not strictly better
    assert not admit(_outcome(True, arrival=40), _outcome(True, arrival=40))
    assert admit(_outcome(True, arrival=50), _outcome(True, arrival=40))


def test_admission_verdict_names_the_first_failing_filter():
    factual_timeout = _outcome(False)
    assert admission_verdict(factual_timeout, _outcome(False)) == "incomplete"
    # incomplete wins even when the retry also harms a neighbour
    assert admission_verdict(factual_timeout, _outcome(False, col=[-1, 20, -1, -1])) == "incomplete"
    assert admission_verdict(_outcome(True, arrival=40), _outcome(True, arrival=50)) == "not_better"
    # completes and outranks the timed-out factual branch, but neighbour 1 collides newly
    assert admission_verdict(factual_timeout, _outcome(True, arrival=60, col=[-1, 20, -1, -1])) == "harms_other"
    assert admission_verdict(factual_timeout, _outcome(True, arrival=60)) == "admitted"
    assert set(ADMISSION_VERDICTS) == {"incomplete", "not_better", "harms_other", "admitted"}
    # a neighbour's collision that also happens, as early, in the factual branch is no harm
    both = _outcome(False, col=[-1, 20, -1, -1])
    assert admission_verdict(both, _outcome(True, arrival=60, col=[-1, 20, -1, -1])) == "admitted"
    assert admission_verdict(both, _outcome(True, arrival=60, col=[-1, 15, -1, -1])) == "harms_other"


def test_admit_rejects_new_collision_of_a_neighbour():
    factual = _outcome(False)
    cand = _outcome(True, arrival=60, col=[-1, -1, 45, -1])
    assert not admit(factual, cand)


def test_admit_rejects_neighbour_collision_earlier_than_factual():
    # Neighbour 2 collides in both branches, but 10 decisions earlier in the candidate.
    # The rank key is identical on the harm count, and the candidate completes, so only
    # the per-vehicle test can reject it.
    factual = _outcome(False, col=[-1, -1, 55, -1])
    cand = _outcome(True, arrival=60, col=[-1, -1, 45, -1])
    assert cand.key > factual.key
    assert not admit(factual, cand)
    # the same collision at the same step or later is not caused by the retry
    assert admit(factual, _outcome(True, arrival=60, col=[-1, -1, 55, -1]))
    assert admit(factual, _outcome(True, arrival=60, col=[-1, -1, 70, -1]))


def test_admit_per_vehicle_test_is_not_a_count():
    # Same number of harmed vehicles, but a different vehicle: vehicle 3 is new.
    factual = _outcome(False, off=[-1, 30, -1, -1])
    cand = _outcome(True, arrival=60, off=[-1, -1, -1, 30])
    assert not admit(factual, cand)


def test_admit_ignores_the_focal_agents_own_events():
    factual = _outcome(False, col=[50, -1, -1, -1])
    cand = _outcome(True, arrival=40, off=[80, -1, -1, -1])  # after arrival it is gone anyway
    assert admit(factual, cand)


def test_admit_checks_vehicles_present_in_either_branch():
    # neighbour 3 is present only in the candidate's world: it cannot have collided in the
    # factual branch, so its collision in the candidate is new harm
    factual = BranchOutcome(focal=0, completed=False, arrival_step=-1, first_collision_step=np.full(4, -1),
                            first_offroad_step=np.full(4, -1), present=[True, True, True, False])
    cand = BranchOutcome(focal=0, completed=True, arrival_step=60, first_collision_step=[-1, -1, -1, 20],
                         first_offroad_step=np.full(4, -1))
    assert admission_verdict(factual, cand) == "harms_other"
    assert not verify(factual, cand)


def test_admit_rejects_mismatched_branches():
    with pytest.raises(ValueError, match="candidate"):
        admit(_outcome(False, focal=0), _outcome(True, arrival=3, focal=1))
    with pytest.raises(ValueError, match="candidate"):
        admit(_outcome(False), _outcome(True, arrival=3, n=5))


def test_branch_outcome_validates_shapes():
    with pytest.raises(ValueError, match="first_offroad_step"):
        BranchOutcome(0, True, 3, np.full(3, -1), np.full(4, -1))
    with pytest.raises(ValueError, match="focal"):
        BranchOutcome(5, True, 3, np.full(3, -1), np.full(3, -1))


# ----------------------------------------------------------------------------- verification + choice


def test_verify_discards_when_rerun_fails():
    factual = _outcome(False)
    # first run: admissible; rerun with fresh draws: the teacher times out too
    assert admit(factual, _outcome(True, arrival=60))
    assert not verify(_outcome(False), _outcome(False))
    # rerun completes but a neighbour now collides earlier than in the factual rerun
    assert not verify(_outcome(False, col=[-1, 70, -1, -1]), _outcome(True, arrival=50, col=[-1, 60, -1, -1]))
    assert verify(_outcome(False), _outcome(True, arrival=62))


def test_verify_passes_when_the_factual_rerun_is_lucky_too():
    # the factual rerun also completes, even earlier: the candidate rerun does not outrank
    # it (admit would reject it), but verification only asks for a clean completion
    # and the per-vehicle test
    lucky = _outcome(True, arrival=40)
    rerun = _outcome(True, arrival=55)
    assert not admit(lucky, rerun)
    assert verify(lucky, rerun)
    # same arrival: still verified
    assert verify(_outcome(True, arrival=55), _outcome(True, arrival=55))
    # a lucky factual rerun does not excuse a new neighbour collision
    assert not verify(lucky, _outcome(True, arrival=55, col=[-1, -1, 60, -1]))


def test_verify_requires_a_clean_completion_of_the_focal_agent():
    factual = _outcome(False)
    # completes, but the focal agent collided or left the road on the way (an "ignore"
    # event rule keeps it driving): not a clean completion
    assert not verify(factual, _outcome(True, arrival=60, col=[30, -1, -1, -1]))
    assert not verify(factual, _outcome(True, arrival=60, off=[30, -1, -1, -1]))
    # an event at decision 0 is an event too (-1 is the only "never")
    assert not verify(factual, _outcome(True, arrival=60, col=[0, -1, -1, -1]))
    assert not verify(factual, _outcome(True, arrival=60, off=[0, -1, -1, -1]))
    # an event of the focal agent in the factual rerun does not matter
    assert verify(_outcome(False, col=[50, -1, -1, -1]), _outcome(True, arrival=60))


def test_verify_per_vehicle_test_against_the_fresh_factual_rerun():
    # neighbour 1 collides at 70 in the factual rerun: the same collision at 70 or later in
    # the candidate rerun is not caused by it; earlier or a new vehicle is
    factual = _outcome(False, col=[-1, 70, -1, -1], off=[-1, -1, 40, -1])
    assert verify(factual, _outcome(True, arrival=50, col=[-1, 70, -1, -1]))
    assert verify(factual, _outcome(True, arrival=50, col=[-1, 80, -1, -1], off=[-1, -1, 45, -1]))
    assert not verify(factual, _outcome(True, arrival=50, col=[-1, 69, -1, -1]))
    assert not verify(factual, _outcome(True, arrival=50, off=[-1, -1, 39, -1]))
    assert not verify(factual, _outcome(True, arrival=50, off=[-1, -1, -1, 60]))
    # events of slots absent from both branches are ignored
    absent = BranchOutcome(focal=0, completed=True, arrival_step=50, first_collision_step=[-1, -1, -1, 20],
                           first_offroad_step=np.full(4, -1), present=[True, True, True, False])
    factual_absent = BranchOutcome(focal=0, completed=False, arrival_step=-1,
                                   first_collision_step=np.full(4, -1), first_offroad_step=np.full(4, -1),
                                   present=[True, True, True, False])
    assert verify(factual_absent, absent)
    with pytest.raises(ValueError, match="candidate_rerun"):
        verify(_outcome(False), _outcome(True, arrival=3, n=5))


def test_choose_teacher_by_rank_and_by_return():
    factual = _outcome(False, col=[-1, -1, 55, -1])
    candidates = [
        _outcome(False, ret=9.0),                                  # incomplete
        _outcome(True, arrival=50, col=[-1, -1, 45, -1], ret=8.0),  # earlier neighbour crash
        _outcome(True, arrival=70, ret=5.0),
        _outcome(True, arrival=60, ret=1.0),
        _outcome(True, arrival=60, ret=2.0),
    ]
    assert choose_teacher(factual, candidates) == 3            # earliest arrival, first of the tie
    assert choose_teacher(factual, candidates[:2]) is None
    with pytest.raises(ValueError, match="selection"):
        choose_teacher(factual, candidates, selection="best")


def test_choose_teacher_by_return_has_no_completion_or_safety_filter():
    # selection by reward: the highest return under its own condition wins, even an
    # incomplete retry or one that crashes a neighbour; nothing is filtered out first
    factual = _outcome(False, col=[-1, -1, 55, -1])
    incomplete = _outcome(False, ret=9.0)
    crash = _outcome(True, arrival=50, col=[-1, -1, 45, -1], ret=8.0)
    clean = _outcome(True, arrival=60, ret=5.0)
    assert not admit(factual, incomplete) and not admit(factual, crash) and admit(factual, clean)
    assert choose_teacher(factual, [clean, crash, incomplete], selection="return") == 2
    assert choose_teacher(factual, [clean, crash], selection="return") == 1
    # a teacher even when no candidate is admissible (rank selection finds none)
    assert choose_teacher(factual, [crash, incomplete], selection="rank") is None
    assert choose_teacher(factual, [crash, incomplete], selection="return") == 1
    # ties: first in panel order; a NaN return never wins
    assert choose_teacher(factual, [_outcome(False, ret=2.0), _outcome(True, arrival=9, ret=2.0)],
                          selection="return") == 0
    assert choose_teacher(factual, [_outcome(False, ret=float("nan")), _outcome(False, ret=-5.0)],
                          selection="return") == 1
    assert choose_teacher(factual, [], selection="return") is None
    with pytest.raises(ValueError, match="candidate"):
        choose_teacher(factual, [_outcome(True, arrival=3, n=5)], selection="return")


def test_return_selection_still_goes_through_verification():
    # the reward-selected retry (incomplete, highest return) is checked by the reruns like
    # any teacher: its rerun must complete cleanly and pass the per-vehicle test
    factual = _outcome(False)
    candidates = [_outcome(True, arrival=60, ret=1.0), _outcome(False, ret=3.0)]
    j = choose_teacher(factual, candidates, selection="return")
    assert j == 1
    assert not verify(_outcome(False), _outcome(False, ret=3.0))          # rerun fails: discarded
    assert verify(_outcome(False), _outcome(True, arrival=70, ret=3.5))   # rerun completes: kept
