"""The seed paper's six adapted post-training baselines (docs/baselines.md), one
sub-package each, in the paper's table order: :mod:`~cpalgo.baselines.spiced`,
:mod:`~cpalgo.baselines.cl4ad`, :mod:`~cpalgo.baselines.dapo`,
:mod:`~cpalgo.baselines.vineppo`, :mod:`~cpalgo.baselines.plannerrft`,
:mod:`~cpalgo.baselines.craft`.

Their shared machinery lives beside them: :mod:`~cpalgo.baselines.continuations` (roots at
interaction states, groups of continuations run on branched simulators, budget
accounting; DAPO, VinePPO, PlannerRFT and CRAFT) and :mod:`~cpalgo.baselines.registry`
(registers the six in :mod:`cpalgo.methods`; importing this package does it, nothing
heavy is imported). Every baseline is a :class:`cpalgo.common.hooked_train.HookedPPO`.
"""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
