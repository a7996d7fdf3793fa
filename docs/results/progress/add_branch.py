"""Convert a flat anchor to a condition-branch network (same function at the start):
python docs/results/progress/add_branch.py ANCHOR.zip OUT.zip [residual|concat]"""
import sys

import numpy as np
from sb3_contrib import RecurrentPPO

from cpalgo.checkpoint import save_model_atomic
from cpalgo.encoders import ConditionConcat, ConditionResidual, add_condition_branch
from cpsim.envs.selfplay import SelfPlayVecEnv

src, out = sys.argv[1], sys.argv[2]
kind = {"residual": ConditionResidual, "concat": ConditionConcat}[sys.argv[3] if len(sys.argv) > 3 else "residual"]
anchor = RecurrentPPO.load(src, device="cpu")
env = SelfPlayVecEnv(num_worlds=2, max_agents=8, num_scenarios=8, seed=0)
start = env.obs_layout.condition.start
kwargs = dict(anchor.policy_kwargs)
kwargs.update(features_extractor_class=kind,
              features_extractor_kwargs=dict(condition_start=start, condition_size=env.obs_layout.condition_features))
hyper = {k: getattr(anchor, k) for k in ("n_steps", "batch_size", "n_epochs", "learning_rate", "gamma", "gae_lambda",
                                         "clip_range", "ent_coef", "vf_coef", "max_grad_norm")}
model = RecurrentPPO(type(anchor.policy), env, policy_kwargs=kwargs, device="cpu", seed=0, **hyper)
print("not copied:", add_condition_branch(anchor.policy, model.policy))
obs = env.reset()
starts = np.ones(obs.shape[0], bool)
act_a, (h_a, c_a) = anchor.predict(obs, episode_start=starts, deterministic=True)
act_m, (h_m, c_m) = model.predict(obs, episode_start=starts, deterministic=True)
assert (act_a == act_m).all() and np.allclose(h_a, h_m, atol=1e-6) and np.allclose(c_a, c_m, atol=1e-6)
print("same actions and LSTM states on", obs.shape[0], "slots")
print("saved", save_model_atomic(model, out))
