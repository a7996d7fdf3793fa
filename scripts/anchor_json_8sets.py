"""Add the shipped anchor's four fresh task sets to zoo/anchor_imitation.json.

    python scripts/anchor_json_8sets.py [RECORD]

The anchor (J16) was chosen over its sibling J17 on task sets 0-3, which therefore flatter it;
sets 4-7 (``docs/results/anchor/seed{4,5,6,7}/summary_{deployment}.csv``) were drawn after the
choice. Adds ``seed4`` ... ``seed7``, ``pooled_fresh_4_sets`` (sets 4-7) and
``pooled_8_sets`` to the ``evaluator`` record, and a sentence with the profile's values
over eight sets to its note; written through a temporary file and a rename. Refuses to run twice.
"""
from __future__ import annotations

import json
import os

from anchor_json import ANCHOR_JSON, HERE, load_folder, pool, write_json


def profile_sentence(p: dict, label: str) -> str:
    """The profile values of a pooled record (Interactive / Random) with their verdicts."""
    splits = ("interactive", "random")
    normal, aggressive, cautious = p["normal"], p["aggressive"], p["cautious"]

    def pair(values: list[float], fmt: str) -> str:
        return " / ".join(format(v, fmt) for v in values)

    def missed(ok: list[bool]) -> str:
        names = [s.capitalize() for s, good in zip(splits, ok) if not good]
        return "met" if not names else " and ".join(names) + " missed"

    score = [normal[s]["score"] for s in splits]
    at_fault = [100 * normal[s]["at_fault_collision"] for s in splits]
    timeout = [100 * normal[s]["timeout"] for s in splits]
    other_failures = [100 * max(normal[s][m] for m in ("at_fault_collision", "non_at_fault_collision", "offroad"))
                      for s in splits]
    sep = [100 * (aggressive[s]["completion"] - normal[s]["completion"]) for s in splits]
    cautious_at_fault = [100 * cautious[s]["at_fault_collision"] for s in splits]
    gaps = []
    for s in splits:
        by_regime = normal[s]["completion_by_regime"]
        regimes = [by_regime[g] for g in ("aggressive", "normal", "cautious")]
        gaps.append(100 * (max(regimes) - min(regimes)))
    return (f"{label} (Interactive / Random): score {pair(score, '.1f')} (>= 50: {missed([v >= 50 for v in score])}), "
            f"at-fault {pair(at_fault, '.1f')} % (<= 10: {missed([v <= 10 for v in at_fault])}), timeout "
            f"{pair(timeout, '.1f')} % (largest failure class, >= 15: "
            f"{missed([t >= 15 and t >= o for t, o in zip(timeout, other_failures)])}), aggressive - normal "
            f"completion {pair(sep, '+.1f')} (>= +10: {missed([v >= 10 for v in sep])}), cautious at-fault "
            f"{pair(cautious_at_fault, '.1f')} % (<= normal's: "
            f"{missed([c <= n for c, n in zip(cautious_at_fault, at_fault)])}), completion gap across the "
            f"aggressive / normal / cautious traffic regimes {pair(gaps, '.2f')} points "
            f"(>= 5: {missed([v >= 5 for v in gaps])}).")


def main() -> None:
    record = json.load(open(ANCHOR_JSON))
    evaluator = record["evaluator"]
    if "seed4" in evaluator:
        raise SystemExit(f"{ANCHOR_JSON} already has the fresh task sets")
    for s in range(4, 8):
        evaluator[f"seed{s}"] = load_folder(os.path.join(HERE, f"seed{s}"), ("interactive", "random"))
    evaluator["pooled_fresh_4_sets"] = pool([evaluator[f"seed{s}"] for s in range(4, 8)])
    evaluator["pooled_8_sets"] = pool([evaluator[f"seed{s}"] for s in range(8)])
    evaluator["note"] += (
        " J16 was chosen over J17 on these four sets, which therefore flatter it. Four fresh sets "
        "(--seed 4 to 7, drawn after the choice) are 'seed4' to 'seed7'. "
        + profile_sentence(evaluator["pooled_fresh_4_sets"], "Over the fresh sets")
        + " " + profile_sentence(evaluator["pooled_8_sets"], "Over all eight sets ('pooled_8_sets')"))
    write_json(ANCHOR_JSON, record)
    print("wrote", os.path.normpath(ANCHOR_JSON))


if __name__ == "__main__":
    main()
