"""Compress a trained recurrent policy into a faster network: factorise, then distill.

:func:`cpalgo.encoders.factorize_input_layers` gives a :class:`~cpalgo.encoders.LinearEncoder`
network whose input projections are close to a flat one's (1.8 % relative squared error, about
13 % in norm, at rank 128 for the shipped anchor). Nearly is not enough for a peaked 12-action policy driving
90 steps (the converted anchor agrees with the original's argmax on about 60 % of live steps),
so :func:`distill_policy` then trains the new network on the original's action probabilities
and values, DAgger style: rollouts in the simulator where each agent is driven either by the
teacher (probability ``beta`` per agent and episode, decaying over rounds) or by the student,
every live step labelled with the teacher's probabilities and value under the teacher's own
recurrent memory of that rollout.

Conditions are p_train draws; ``panel_share`` of the agents get a panel profile's style
fields and ``eval_task_share`` the evaluation goal criterion's task fields, so the styles and
the task the policy is deployed on are covered, not only p_train's interior.

``counterplay compress-anchor`` runs both steps on a checkpoint.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch as th
import torch.nn.functional as F

from cpalgo.anchor.imitation import _sequence_forward, train_on_episodes
from cpalgo.common.checks import UsageError, check_out_path, load_womd_option, non_negative_int, set_threads
from cpalgo.common.policy_utils import policy_step_logits, zero_states
from cpsim.conditions import sample_conditions, with_eval_task, with_panel_share
from cpsim.config import Controller, known_fields

__all__ = ["DistillConfig", "TeacherBatch", "collect_teacher_episodes", "distill_losses", "distill_policy"]


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """Schedule of :func:`distill_policy`.

    Attributes:
        rounds: DAgger rounds (collect, then train on the kept rounds); 0 trains nothing.
        num_worlds: worlds per round (one episode each).
        epochs: passes over the kept data per round.
        keep_rounds: rounds of data kept.
        batch_sequences: episodes (agent slots) per minibatch.
        learning_rate, max_grad_norm: Adam settings.
        value_coef: weight of the value MSE next to the KL.
        beta: probability that the teacher drives an agent in round 0; round i uses
            ``beta * decay ** i``.
        decay: see ``beta``.
        panel_share: share of agents whose style fields are a random panel profile's.
        eval_task_share: share of agents with the evaluation goal criterion's task fields.
    """

    rounds: int = 8
    num_worlds: int = 64
    epochs: int = 4
    keep_rounds: int = 4
    batch_sequences: int = 128
    learning_rate: float = 3e-4
    max_grad_norm: float = 0.5
    value_coef: float = 0.5
    beta: float = 0.5
    decay: float = 0.5
    panel_share: float = 0.5
    eval_task_share: float = 0.25

    def __post_init__(self) -> None:
        for name in ("rounds", "num_worlds", "epochs", "keep_rounds", "batch_sequences"):
            if not isinstance(getattr(self, name), (int, np.integer)) or isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: must be an integer, got {getattr(self, name)!r}")
        for name in ("learning_rate", "max_grad_norm", "value_coef", "beta", "decay", "panel_share",
                     "eval_task_share"):
            if not np.isfinite(float(getattr(self, name))):
                raise ValueError(f"{name}: must be a finite number, got {getattr(self, name)!r}")
        if int(self.rounds) < 0:
            raise ValueError(f"rounds: must be >= 0 (0: no distillation), got {self.rounds!r}")
        for name in ("num_worlds", "epochs", "keep_rounds", "batch_sequences"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name}: must be a positive integer, got {getattr(self, name)!r}")
        for name in ("learning_rate", "max_grad_norm"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)!r}")
        if float(self.value_coef) < 0:
            raise ValueError(f"value_coef: must be >= 0, got {self.value_coef!r}")
        for name in ("beta", "decay", "panel_share", "eval_task_share"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"{name}: must lie in [0, 1], got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "DistillConfig":
        return cls(**known_fields(cls, values, "DistillConfig"))


@dataclasses.dataclass
class TeacherBatch:
    """One round's episodes, time-major.

    Attributes:
        obs: (T, N, D) float32 observations (0 where the slot is not a live policy agent).
        log_probs: (T, N, n_actions) float32 teacher log-probabilities.
        values: (T, N) float32 teacher values.
        mask: (T, N) bool, live policy agents.
        kl: mean KL(teacher || student) over live steps during the rollout (before training).
        agreement: share of live steps where the student's argmax equals the teacher's.
    """

    obs: th.Tensor
    log_probs: th.Tensor
    values: th.Tensor
    mask: th.Tensor
    kl: float
    agreement: float


def _draw_conditions(rng: np.random.Generator, shape: tuple[int, int], panel_share: float,
                     eval_task_share: float) -> np.ndarray:
    """p_train draws (W, A, 10); some agents get a panel style or the evaluation task fields."""
    conds = with_panel_share(rng, sample_conditions(rng, shape), panel_share)
    return with_eval_task(rng, conds, eval_task_share)


@th.no_grad()
def collect_teacher_episodes(student: Any, teacher: Any, sim: Any, beta: float, rng: np.random.Generator,
                             config: DistillConfig) -> TeacherBatch:
    """One episode in every world of ``sim``, labelled with the teacher's probabilities.

    Each POLICY agent is driven by the teacher with probability ``beta`` (per agent, for the
    whole episode) and by the student otherwise (sampled actions); both keep their own LSTM
    memory of the rollout.
    """
    from cpsim.envs.selfplay import OBS_BOUND

    W, A = sim.num_worlds, sim.max_agents
    N = W * A
    sim.reset(scenario_index=rng.integers(0, sim.num_scenarios, size=W),
              conditions=_draw_conditions(rng, (W, A), config.panel_share, config.eval_task_share))
    T = sim.config.episode_steps
    device = student.device
    s_states, t_states = zero_states(student, N, device), zero_states(teacher, N, device)
    by_teacher = th.as_tensor(rng.random(N) < beta, device=device)
    n_actions = int(student.action_space.n)
    obs_buf = th.zeros((T, N, sim.obs_layout.size), dtype=th.float32)
    logp_buf = th.zeros((T, N, n_actions), dtype=th.float32)
    value_buf = th.zeros((T, N), dtype=th.float32)
    mask = th.zeros((T, N), dtype=th.bool)
    starts = th.ones(N, device=device)
    kl_sum = agree = 0.0
    steps = T
    for t in range(T):
        live = ((sim.controllers == int(Controller.POLICY)) & sim.alive).reshape(-1).to(device)
        obs = (sim.obs.reshape(N, -1).clamp(-OBS_BOUND, OBS_BOUND) * live.reshape(-1, 1)).to(device)
        t_logits, t_values, t_states = policy_step_logits(teacher, obs, t_states, starts)
        s_logits, _, s_states = policy_step_logits(student, obs, s_states, starts)
        starts = th.zeros(N, device=device)
        t_logp = th.log_softmax(t_logits, -1)
        s_logp = th.log_softmax(s_logits, -1)
        kl = (t_logp.exp() * (t_logp - s_logp)).sum(-1)
        kl_sum += float(kl[live].sum())
        agree += float(((t_logits.argmax(-1) == s_logits.argmax(-1)) & live).sum())
        action = th.where(by_teacher, th.distributions.Categorical(logits=t_logits).sample(),
                          th.distributions.Categorical(logits=s_logits).sample())
        obs_buf[t], logp_buf[t], value_buf[t], mask[t] = obs.cpu(), t_logp.cpu(), t_values.reshape(-1).cpu(), live.cpu()
        sim.step(action.reshape(W, A).to(th.int32).to(sim.obs.device))
        if bool(sim.world_done.all()):
            steps = t + 1
            break
    n = max(int(mask.sum()), 1)
    return TeacherBatch(obs_buf[:steps], logp_buf[:steps], value_buf[:steps], mask[:steps], kl_sum / n, agree / n)


def distill_losses(student: Any, obs: th.Tensor, log_probs: th.Tensor, values: th.Tensor,
                   mask: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """Masked mean KL(teacher || student) over actions and MSE to the teacher's values.

    Args:
        obs: (T, B, D) whole episodes from a zero memory; log_probs: (T, B, n_actions)
            teacher log-probabilities; values: (T, B); mask: (T, B) bool.
    """
    logits, student_values = _sequence_forward(student, obs)
    m = mask.float()
    n = m.sum().clamp(min=1.0)
    kl = (log_probs.exp() * (log_probs - F.log_softmax(logits, -1))).sum(-1)
    return (kl * m).sum() / n, (((student_values - values) ** 2) * m).sum() / n


def distill_policy(model: Any, teacher: Any, scenarios: Sequence[Any], config: DistillConfig | None = None,
                   sim_config: Any = None, max_agents: int = 8, seed: int = 0,
                   log: Callable[[str], None] | None = print,
                   on_round: Callable[[dict[str, float]], None] | None = None) -> list[dict[str, float]]:
    """DAgger distillation of ``teacher`` (a recurrent policy) into ``model.policy``.

    Args:
        model: RecurrentPPO-family model (discrete actions) whose policy is trained in place.
        teacher: the frozen recurrent policy (same observation and action spaces).
        scenarios: training scenarios of the rollouts.
        config: the schedule (:class:`DistillConfig`).
        sim_config: SimConfig of the rollouts (default: cpsim's).
        max_agents: agent slots per world.
        seed: seed of scenario, condition, coin and minibatch draws.
        log: called with one line per round (None: silent).
        on_round: called with each round's row after it trained (e.g. to checkpoint).
    Returns:
        one dict per round: beta, kl and agreement of the round's rollouts before training on
        them, kl_train and value_mse (mean over the round's last epoch), transitions, seconds.
    """
    from cpsim.simulator import Simulator

    cfg = config or DistillConfig()
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("scenarios: empty")
    policy = model.policy
    if teacher.observation_space.shape != policy.observation_space.shape:
        raise ValueError(f"teacher: observation shape {teacher.observation_space.shape} differs from the "
                         f"student's {policy.observation_space.shape}")
    if getattr(teacher.action_space, "n", None) != getattr(policy.action_space, "n", None):
        raise ValueError(f"teacher: action space {teacher.action_space} differs from the student's "
                         f"{policy.action_space}")
    sim = Simulator(scenarios, num_worlds=cfg.num_worlds, max_agents=max_agents, config=sim_config, seed=seed)
    if policy.observation_space.shape != (sim.obs_layout.size,):
        raise ValueError(f"model: observation shape {policy.observation_space.shape} does not match the "
                         f"simulator's ({sim.obs_layout.size},)")
    teacher.set_training_mode(False)
    rng = np.random.default_rng(seed)
    gen = th.Generator().manual_seed(seed)
    optimizer = th.optim.Adam(policy.parameters(), lr=cfg.learning_rate)
    data: list[TeacherBatch] = []
    history: list[dict[str, float]] = []
    for it in range(cfg.rounds):
        t0 = time.perf_counter()
        beta = cfg.beta * cfg.decay ** it
        policy.set_training_mode(False)
        batch = collect_teacher_episodes(policy, teacher, sim, beta, rng, cfg)
        data = (data + [batch])[-cfg.keep_rounds:]
        policy.set_training_mode(True)

        def losses(b: TeacherBatch, idx: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
            dev = policy.device
            return distill_losses(policy, b.obs[:, idx].to(dev), b.log_probs[:, idx].to(dev),
                                  b.values[:, idx].to(dev), b.mask[:, idx].to(dev))

        kl_mean, mse_mean = train_on_episodes(policy, optimizer, data, losses, cfg.epochs, cfg.batch_sequences,
                                              gen, cfg.value_coef, cfg.max_grad_norm)
        policy.set_training_mode(False)
        row = {"round": it, "beta": beta, "kl": batch.kl, "agreement": batch.agreement,
               "kl_train": kl_mean, "value_mse": mse_mean,
               "transitions": int(batch.mask.sum()), "seconds": time.perf_counter() - t0}
        history.append(row)
        if log is not None:
            log(f"distillation round {it}: beta {beta:.3f}  rollout KL {batch.kl:.4f}  agreement "
                f"{batch.agreement:.1%}  train KL {row['kl_train']:.4f}  value mse {row['value_mse']:.4f}  "
                f"{row['transitions']} transitions  {row['seconds']:.0f} s")
        if on_round is not None:
            on_round(row)
    return history


def compress_checkpoint(anchor: str, out: str, features_dim: int = 128, config: DistillConfig | None = None,
                        scenarios: Sequence[Any] | None = None, max_agents: int = 8, fit_worlds: int = 64,
                        seed: int = 0, log: Callable[[str], None] | None = print,
                        init: str | None = None) -> dict[str, Any]:
    """Factorise a flat RecurrentPPO checkpoint into the encoder network, distill, save.

    Args:
        anchor: SB3 checkpoint of a flat recurrent policy (``MlpLstmPolicy``, no encoder).
        out: where to write the new checkpoint (atomically; a RecurrentPPO with the anchor's
            PPO settings (n_steps, batch_size, n_epochs, learning_rate, gamma, gae_lambda,
            clip_range, ent_coef, vf_coef, max_grad_norm) and ``policy_kwargs`` plus the encoder).
        features_dim: the encoder's width (rank of the factorisation).
        config: the distillation schedule (``rounds=0`` keeps the bare factorisation).
        scenarios: rollout scenarios (default: the procedural training pool of 192).
        max_agents: agent slots per world of the rollouts.
        fit_worlds: worlds of the teacher-driven episode whose observations fit the factorisation.
        init: an earlier output of this function to continue distilling (no new factorisation).
    Returns:
        a JSON-able report: the fit (:func:`factorize_input_layers`), the rounds, the wall time.
    """
    from sb3_contrib import RecurrentPPO

    from cpalgo.checkpoint import save_model_atomic
    from cpalgo.encoders import LinearEncoder, encoder_policy_kwargs, factorize_input_layers
    from cpsim.envs.selfplay import SelfPlayVecEnv, resolve_scenarios
    from cpsim.simulator import Simulator

    t0 = time.perf_counter()
    cfg = config if config is not None else DistillConfig()
    try:
        teacher = RecurrentPPO.load(anchor, device="cpu")
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise ValueError(f"anchor: cannot load {anchor!r} as a RecurrentPPO checkpoint ({exc})") from None
    if isinstance(teacher.policy.features_extractor, LinearEncoder):
        raise ValueError(f"anchor: {anchor} already has a LinearEncoder")
    scenarios = list(scenarios) if scenarios is not None else resolve_scenarios(num_scenarios=192, seed=seed)
    env = SelfPlayVecEnv(scenarios, num_worlds=1, max_agents=max_agents, seed=seed)
    if teacher.observation_space.shape != env.observation_space.shape or teacher.action_space != env.action_space:
        raise ValueError(f"anchor: {anchor} observes {teacher.observation_space.shape} and acts in "
                         f"{teacher.action_space}; the self-play env {env.observation_space.shape} and "
                         f"{env.action_space}")
    hyper = {name: getattr(teacher, name) for name in (
        "n_steps", "batch_size", "n_epochs", "learning_rate", "gamma", "gae_lambda", "clip_range", "ent_coef",
        "vf_coef", "max_grad_norm")}
    model = type(teacher)("MlpLstmPolicy", env, seed=seed, device="cpu",
                          policy_kwargs=encoder_policy_kwargs(teacher.policy_kwargs, features_dim), **hyper)
    fit: dict[str, Any] = {}
    if init is not None:
        try:
            model.set_parameters(init, exact_match=True, device="cpu")
        except Exception as exc:  # noqa: BLE001 - reported with the file name
            raise ValueError(f"init: {init} is not a {features_dim}-feature encoder network of this anchor "
                             f"({exc})") from None
        fit = {"init": str(init)}
    else:
        sim = Simulator(scenarios, num_worlds=fit_worlds, max_agents=max_agents, seed=seed + 1)
        fit_batch = collect_teacher_episodes(teacher.policy, teacher.policy, sim, 1.0,
                                             np.random.default_rng(seed + 1), cfg)
        observations = fit_batch.obs[fit_batch.mask].numpy()
        fit = factorize_input_layers(teacher.policy, model.policy, observations)
        if log is not None:
            log(f"factorised to rank {features_dim} on {observations.shape[0]} observations: relative error "
                f"{fit['relative_error']:.4f} (actor {fit['actor_relative_error']:.4f})")
    # a checkpoint after every round: a long run that is cut off keeps its last good round
    rounds = distill_policy(model, teacher.policy, scenarios, cfg, max_agents=max_agents, seed=seed, log=log,
                            on_round=lambda _row: save_model_atomic(model, out))
    path = save_model_atomic(model, out)
    return {"anchor": str(anchor), "out": str(path), "features_dim": int(features_dim), "fit": fit,
            "config": dataclasses.asdict(cfg), "rounds": rounds, "wall_s": round(time.perf_counter() - t0, 1)}


def add_command(add: Callable[..., Any]) -> None:
    """Add ``compress-anchor`` with ``cpalgo.cli``'s ``add(name, help, description)``."""
    p = add("compress-anchor", "convert a flat anchor into the faster encoder network",
            "Factorise the anchor's input layers into a LinearEncoder (cpalgo.encoders) of --features-dim "
            "outputs, then distill the anchor into it (cpalgo.anchor.compress.distill_policy: DAgger rounds on "
            "the anchor's action probabilities and values). Writes the checkpoint and a JSON report "
            "beside it.")
    p.add_argument("--anchor", default="zoo/anchor_imitation.zip", metavar="ZIP", help="flat anchor checkpoint")
    p.add_argument("--out", default="runs/anchor_fast/anchor.zip", metavar="ZIP", help="checkpoint to write")
    p.add_argument("--init", default=None, metavar="ZIP",
                   help="continue distilling this earlier output (skips the factorisation)")
    p.add_argument("--features-dim", type=int, default=128, metavar="R", help="encoder width (rank)")
    p.add_argument("--rounds", type=int, default=DistillConfig.rounds, metavar="N",
                   help="distillation rounds (0: the factorisation only)")
    p.add_argument("--worlds", type=int, default=DistillConfig.num_worlds, metavar="W", help="worlds per round")
    p.add_argument("--epochs", type=int, default=DistillConfig.epochs, metavar="N", help="passes per round")
    p.add_argument("--learning-rate", type=float, default=DistillConfig.learning_rate, metavar="LR",
                   help="Adam learning rate of the distillation")
    p.add_argument("--beta", type=float, default=DistillConfig.beta, metavar="P",
                   help="probability that the anchor drives an agent in the first round (halved every round; "
                        "0 when continuing with --init drives with the student only)")
    p.add_argument("--add-womd", default=None, metavar="DIR",
                   help="add the WOMD scenes of this folder to the procedural training pool")
    p.add_argument("--scenarios", type=int, default=192, metavar="N",
                   help="procedural training scenarios of the rollouts (the anchor recipes' pool)")
    p.add_argument("--max-agents", type=int, default=8, metavar="A", help="agent slots per world")
    p.add_argument("--seed", type=non_negative_int, default=0,
                   help="seed of the procedural pool, the rollouts and the initialisation")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.set_defaults(func=_cmd_compress)


def _cmd_compress(args: Any) -> int:
    import json
    import os
    import sys
    from pathlib import Path

    from cpalgo.recipes import resolve_path
    from cpsim.atomic import write_text_atomic
    from cpsim.envs.selfplay import resolve_scenarios

    set_threads(args.threads)
    anchor = resolve_path(args.anchor)
    if not os.path.isfile(anchor):
        raise UsageError(f"--anchor: no such checkpoint {args.anchor!r}")
    if os.path.abspath(args.out) == os.path.abspath(anchor):
        raise UsageError("--out: must differ from --anchor (the anchor is the teacher of every round)")
    check_out_path(args.out, "--out", folder=False)
    for name in ("features_dim", "worlds", "epochs", "max_agents", "scenarios"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')}: must be a positive integer, got {getattr(args, name)}")
    scenarios = resolve_scenarios(num_scenarios=args.scenarios, seed=args.seed)
    if args.add_womd:
        scenarios = scenarios + load_womd_option(args.add_womd)
    try:
        cfg = DistillConfig(rounds=args.rounds, num_worlds=args.worlds, epochs=args.epochs,
                            learning_rate=args.learning_rate, beta=args.beta)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.init is not None and not os.path.isfile(args.init):
        raise UsageError(f"--init: no such checkpoint {args.init!r}")
    try:
        report = compress_checkpoint(anchor, args.out, args.features_dim, cfg, scenarios, args.max_agents,
                                     seed=args.seed, init=args.init)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    report["command"] = "counterplay " + " ".join(sys.argv[1:])
    json_path = Path(str(Path(report["out"]).with_suffix("")) + ".json")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(json_path, json.dumps(report, indent=1))
    print(f"compressed anchor saved to {report['out']} in {report['wall_s']:.0f} s (report {json_path})")
    return 0
