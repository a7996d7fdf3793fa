"""CounterPlay: roots, backtracking, branches, ranking, verification, distillation, budget."""

from cpalgo.counterplay.search import BranchOutcome, admit, choose_teacher, rank_branches, rank_key, select_root, verify

__all__ = ["BranchOutcome", "admit", "choose_teacher", "rank_branches", "rank_key", "select_root", "verify"]
