"""Score the reactive teacher with a given ReactiveStyle in the evaluator (the sweep behind
`ReactiveStyle`'s defaults; docs/results/README.md, "The reactive teacher, version 2").

    python docs/results/anchor_failures/teacher_sweep.py --schedule 0.95 1.35 --curve 2.5 3.0 \
        --exponent 0.35 -- --policy reactive --split both --n 60 --deploy normal --no-plots --out runs/t

Everything after ``--`` goes to ``python -m cpalgo.evaluate``; ``--policy reactive`` there
makes the teacher the ego, and this script gives it the style built from the options here
(``--curve 0 0``: no curve speed limit).
"""

from __future__ import annotations

import argparse
import sys

from cpalgo.evaluate import runner
from cpalgo.evaluate.__main__ import main as evaluate_main
from cpsim.expert import ReactiveStyle, make_expert


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        raise SystemExit("teacher_sweep: put the evaluator's arguments after '--'")
    cut = argv.index("--")
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--schedule", nargs=2, type=float, default=ReactiveStyle.schedule, metavar=("CAUTIOUS", "BOLD"))
    p.add_argument("--curve", nargs=2, type=float, default=ReactiveStyle.curve_lat_accel, metavar=("CAUTIOUS", "BOLD"),
                   help="curve lateral acceleration, m/s^2 (0 0: no curve speed limit)")
    p.add_argument("--exponent", type=float, default=ReactiveStyle.exponent)
    args = p.parse_args(argv[:cut])
    curve = None if max(args.curve) <= 0 else tuple(args.curve)
    style = ReactiveStyle(schedule=tuple(args.schedule), curve_lat_accel=curve, exponent=args.exponent)
    print(f"teacher style: {style}", flush=True)

    def bind(self, sim) -> None:  # the evaluator's teacher ego, with this style
        self._expert = make_expert(self.name, sim, style=style)

    runner.TeacherEgo.bind = bind
    return evaluate_main(argv[cut + 1:])


if __name__ == "__main__":
    sys.exit(main())
