"""The anchor pipeline: how a reward-conditioned self-play policy is made and checked.

The shipped anchor ``zoo/anchor.zip`` is self-play PPO from scratch in resumable pieces
(:mod:`~cpalgo.anchor.selfplay`, ``counterplay train-anchor --run-dir``), exported by
:mod:`~cpalgo.anchor.export`. The teacher-imitation anchor ``zoo/anchor_imitation.zip``
came from the other stages, in the order ``counterplay train-anchor`` runs them:

* :mod:`~cpalgo.anchor.imitation`: DAgger warm start from the tracking expert
  (:func:`imitate_expert`).
* :mod:`~cpalgo.anchor.teacher_ppo`: teacher-regularised self-play PPO that keeps the
  teacher's styles (:class:`TeacherPPO`), exported as plain ``RecurrentPPO``
  (:func:`export_recurrent_ppo`).
* :mod:`~cpalgo.anchor.compress`: factorise and distill into the faster encoder network
  (``counterplay compress-anchor``, :func:`compress_checkpoint`).
* :mod:`~cpalgo.anchor.outcomes`: self-play outcome rates on held-out tasks, the anchor's
  report card (``counterplay outcomes``, :func:`selfplay_outcomes`).
* :mod:`~cpalgo.anchor.export`: a self-play run's latest checkpoint as a shippable anchor
  with its provenance record (``counterplay export-anchor``, :func:`export_anchor`).

Names load on first use (torch and SB3 are imported then).
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports

_LAZY = {
    "ImitationConfig": "cpalgo.anchor.imitation", "imitate_expert": "cpalgo.anchor.imitation",
    "TeacherPPO": "cpalgo.anchor.teacher_ppo", "export_recurrent_ppo": "cpalgo.anchor.teacher_ppo",
    "DistillConfig": "cpalgo.anchor.compress", "distill_policy": "cpalgo.anchor.compress",
    "compress_checkpoint": "cpalgo.anchor.compress",
    "OutcomeRates": "cpalgo.anchor.outcomes", "selfplay_outcomes": "cpalgo.anchor.outcomes",
    "expert_outcomes": "cpalgo.anchor.outcomes",
    "export_anchor": "cpalgo.anchor.export",
}
__getattr__, __dir__ = lazy_exports("cpalgo.anchor", _LAZY, globals())
__all__ = list(_LAZY)
