"""Long PPO-Continue from the compressed anchor (issue 12: 'longer PPO with the faster trainer').

Chunks of CHUNK live transitions; a snapshot (plain RecurrentPPO) after each; resumes from the last.
    python -u docs/results/long_ppo/long_ppo.py OUT CHUNK TOTAL EVAL_TASK_SHARE
    (env: THREADS, LR, INIT, N_STEPS (32), BATCH (2048), WOMD (1: add the 40 WOMD training scenes))
    python -u docs/results/long_ppo/long_ppo.py runs/long_ppo/share05 3e6 4.5e7 0.5
    docs/results/long_ppo/watch.sh runs/long_ppo/share05 2     # evaluates every 2nd snapshot
"""
import glob
import json
import os
import sys
import time

import torch
from stable_baselines3.common.vec_env import VecMonitor

import cpsim
from cpalgo.checkpoint import save_model_atomic
from cpalgo.cli import load_womd_option
from cpalgo.counterplay.algorithm import CounterPlay
from cpalgo.encoders import LinearEncoder
from cpalgo.teacher_ppo import export_recurrent_ppo
from cpsim.envs.selfplay import resolve_scenarios


def main() -> None:
    out_dir, chunk, total, share = sys.argv[1], int(float(sys.argv[2])), int(float(sys.argv[3])), float(sys.argv[4])
    torch.set_num_threads(int(os.environ.get("THREADS", "2")))
    os.makedirs(out_dir, exist_ok=True)
    seed = 11
    pool = resolve_scenarios(family=None, num_scenarios=192, seed=seed)
    if os.environ.get("WOMD", "1") == "1":
        pool += load_womd_option("../shared/data/womd/train")
    env = VecMonitor(cpsim.SelfPlayVecEnv(num_worlds=64, max_agents=8, scenarios=pool, dynamics="jerk",
                                          condition="train", eval_task_share=share, seed=seed))
    net = dict(lstm_hidden_size=128, enable_critic_lstm=False, net_arch=dict(pi=[128, 128], vf=[128, 128]),
               features_extractor_class=LinearEncoder, features_extractor_kwargs=dict(features_dim=128))
    kw = dict(n_steps=int(os.environ.get("N_STEPS", "32")), batch_size=int(os.environ.get("BATCH", "2048")),
              n_epochs=3, learning_rate=float(os.environ.get("LR", "1e-4")),
              gamma=0.99, gae_lambda=0.95, clip_range=0.2, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5,
              policy_kwargs=net)
    model = CounterPlay("MlpLstmPolicy", env, counterfactual=False, seed=seed, **kw)
    done = sorted(glob.glob(f"{out_dir}/ck_*.zip"))
    start = done[-1] if done else os.environ.get("INIT", "zoo/anchor_fast.zip")
    first = int(done[-1].split("_")[-1][:-4]) + 1 if done else 1
    model.set_parameters(start, exact_match=True)
    print("start", start, "chunk", first - 1, flush=True)
    t0 = time.perf_counter()
    for k in range(first, total // chunk + 1):
        model.learn(chunk, reset_num_timesteps=True)
        save_model_atomic(export_recurrent_ppo(model, "MlpLstmPolicy", env, seed=seed, **kw),
                          f"{out_dir}/ck_{k:02d}.zip")
        print(json.dumps({"chunk": k, "transitions": k * chunk, "wall_s": round(time.perf_counter() - t0, 1)}),
              flush=True)


if __name__ == "__main__":
    main()
