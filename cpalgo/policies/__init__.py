"""Recurrent policies: sb3-contrib's with a fused sequence LSTM (:mod:`cpalgo.policies.fused`)
and BehaviorBench's conditioned network shape (:mod:`cpalgo.policies.behavior`).

Both are drop-in policy classes for plain ``RecurrentPPO``, ``CounterPlay`` and the anchor
trainer::

    from sb3_contrib import RecurrentPPO
    from cpalgo.policies import BehaviorLstmPolicy, MlpLstmPolicy
    RecurrentPPO(MlpLstmPolicy, env)
    CounterPlay("BehaviorLstmPolicy", env)
"""

from cpalgo.policies.behavior import BehaviorEncoder, BehaviorLstmPolicy
from cpalgo.policies.fused import (
    BUCKET_MIN_PADDING,
    CnnLstmPolicy,
    FusedLstmMixin,
    MlpLstmPolicy,
    MultiInputLstmPolicy,
    fused_process_sequence,
    lengths_from_mask,
    sequence_lengths,
)

#: names accepted by ``CounterPlay(policy=...)``: the fused versions of sb3-contrib's, and
#: BehaviorBench's network
POLICY_ALIASES = {
    "MlpLstmPolicy": MlpLstmPolicy,
    "CnnLstmPolicy": CnnLstmPolicy,
    "MultiInputLstmPolicy": MultiInputLstmPolicy,
    "BehaviorLstmPolicy": BehaviorLstmPolicy,
}

__all__ = [
    "fused_process_sequence", "sequence_lengths", "lengths_from_mask", "FusedLstmMixin", "MlpLstmPolicy",
    "CnnLstmPolicy", "MultiInputLstmPolicy", "BehaviorEncoder", "BehaviorLstmPolicy", "POLICY_ALIASES",
    "BUCKET_MIN_PADDING",
]
