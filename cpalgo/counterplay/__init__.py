"""CounterPlay: roots, backtracking, branches, ranking, verification, distillation, budget."""

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

__all__ = ["ADMISSION_VERDICTS", "BranchOutcome", "admission_verdict", "admit", "choose_teacher", "rank_branches",
           "rank_key", "select_root", "verify"]
