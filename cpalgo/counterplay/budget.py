"""Budget accounting of CounterPlay post-training.

B_post = main + factual + candidate (+ verification) transitions. One transition is one
live agent stepping once: every live agent of every branch world counts, rejected retries
included. The searches of generation g run during generation g+1; their branch
transitions are capped at ``branch_cap`` times g's main transitions (the allowance opened
at the end of g's rollout) and by what is left of ``post_budget``. The main rollout stops
at the step where the total reaches ``post_budget`` (``CounterPlay.collect_rollouts``), so a
run ends within one step of live agents of its budget.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

__all__ = ["Budget"]


@dataclass
class Budget:
    """Running transition totals (agent steps).

    Attributes:
        branch_cap: cap of branch transitions per generation, as a share of that
            generation's main transitions (> 0).
        post_budget: stop ``learn`` once ``total`` reaches it (``None``: no limit).
        main, factual, candidate, verification: running totals since construction.
        generation_main, generation_branch: totals of the generation in progress.
        allowance_main: main transitions of the generation whose searches run now (the
            cap applies to them); allowance_used: branch transitions those searches ran.
        generations: completed generations.
    """

    branch_cap: float = 0.5
    post_budget: int | None = None
    main: int = 0
    factual: int = 0
    candidate: int = 0
    verification: int = 0
    generation_main: int = 0
    generation_branch: int = 0
    allowance_main: int = 0
    allowance_used: int = 0
    generations: int = 0
    history: list[dict[str, int]] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if not self.branch_cap > 0:
            raise ValueError(f"branch_cap: must be > 0, got {self.branch_cap!r}")
        if self.post_budget is not None and not self.post_budget > 0:
            raise ValueError(f"post_budget: must be > 0 or None, got {self.post_budget!r}")

    # ------------------------------------------------------------------ totals
    @property
    def branch(self) -> int:
        """All branch transitions so far (factual + candidate + verification)."""
        return self.factual + self.candidate + self.verification

    @property
    def total(self) -> int:
        """B_post so far: main + every branch transition."""
        return self.main + self.branch

    @property
    def branch_share(self) -> float:
        """Share of branch transitions in the total (0 when nothing ran)."""
        return self.branch / self.total if self.total else 0.0

    @property
    def exhausted(self) -> bool:
        """Whether ``post_budget`` is set and reached."""
        return self.post_budget is not None and self.total >= self.post_budget

    # ------------------------------------------------------------------ generation
    def start_generation(self) -> None:
        self.generation_main = 0
        self.generation_branch = 0

    def add_main(self, transitions: int) -> None:
        self.main += int(transitions)
        self.generation_main += int(transitions)

    def open_allowance(self, main_transitions: int) -> None:
        """The searches of a generation with ``main_transitions`` main transitions start:
        they may run ``branch_cap`` times as many branch transitions."""
        self.allowance_main = int(main_transitions)
        self.allowance_used = 0

    @property
    def remaining(self) -> int | None:
        """Transitions left before ``post_budget`` (None: no limit)."""
        return None if self.post_budget is None else max(0, int(self.post_budget) - self.total)

    @property
    def generation_allowance(self) -> int:
        """Branch transitions the searches now running may still use: under the cap, and
        never past ``post_budget`` (so no branch work overshoots the budget)."""
        allowance = max(0, int(self.branch_cap * self.allowance_main) - self.allowance_used)
        left = self.remaining
        return allowance if left is None else min(allowance, left)

    def fits(self, projected: int) -> bool:
        """Whether a projected number of branch transitions still fits this generation."""
        return int(projected) <= self.generation_allowance

    def add_branch(self, factual: int = 0, candidate: int = 0, verification: int = 0) -> None:
        """Record branch transitions actually run (each argument: agent steps)."""
        self.factual += int(factual)
        self.candidate += int(candidate)
        self.verification += int(verification)
        n = int(factual) + int(candidate) + int(verification)
        self.generation_branch += n
        self.allowance_used += n

    def end_generation(self) -> dict[str, int]:
        """Close the generation; returns and keeps its summary."""
        self.generations += 1
        summary = {"main": self.generation_main, "branch": self.generation_branch,
                   "cap_main": self.allowance_main}
        self.history.append(summary)
        return summary

    def as_dict(self) -> dict[str, float]:
        """Running totals for logging and the CLI summary."""
        d = {k: v for k, v in asdict(self).items() if k != "history"}
        d.update(branch=self.branch, total=self.total, branch_share=self.branch_share)
        return d
