"""Agents for cable insertion: Stable-Baselines3 TD3 with scripted demonstrations in its replay buffer, on
keypoint observations or on a beta-VAE latent of the views (the baseline), trained as a resumable run.

A run folder ``OUT/`` holds ``config.json`` (the :class:`AgentConfig`), ``vae.pt`` (beta-VAE agent),
``checkpoint/`` (``agent.pt``: the policy's and optimizers' state dicts; ``replay.npz``: the filled part of
the replay buffer; ``state.json``: environment steps, gradient updates, episodes) and ``progress.json`` (the
evaluations so far). A checkpoint is written every ``checkpoint_every`` environment steps, all its files
into a new folder that then replaces the previous one, so a killed run resumes (``--resume``) from its last
complete checkpoint with its replay buffer (:mod:`s3k.robot.agent_checkpoint`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import torch as th
import torch.nn.functional as F

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_write_json
from s3k.base.messages import say
from s3k.robot.agent_checkpoint import checkpoint_folder, load_checkpoint, save_checkpoint
from s3k.robot.detect import RunDetector
from s3k.robot.insertion_env import KEYPOINTS, InsertionEnv, scripted_action

AGENTS = ("keypoints", "beta_vae")


def _field(default, text: str):
    return dataclasses.field(default=default, metadata={"help": text})


@dataclasses.dataclass
class AgentConfig:
    """One agent training run; every field's meaning is in its ``metadata["help"]`` (the ``--help`` of
    ``s3k robot train-agent``)."""

    agent: str = _field("keypoints", "keypoints (observations: gripper state + 3D keypoints) or beta_vae "
                                     "(gripper state + a beta-VAE latent of the four views)")
    steps: int = _field(20000, "environment steps to train for, in all (--resume continues towards it)")
    seed: int = _field(0, "seed of the agent, the environment and the demonstrations")
    demos: int = _field(30, "scripted demonstration episodes put in the replay buffer before training")
    checkpoint_every: int = _field(1000, "environment steps between checkpoints of agent and replay buffer")
    eval_episodes: int = _field(10, "episodes of the deterministic policy in each evaluation (the same "
                                    "episodes every time)")
    eval_every: int = _field(0, "environment steps between evaluations of the deterministic policy, on a "
                                "separate environment, for the success-rate curve (0: at every checkpoint); "
                                "the last one is at --steps")
    learning_starts: int = _field(0, "the agent's own environment steps, acting at random, before gradient "
                                     "updates begin (0: the pretrained policy acts from the first step; "
                                     "random actions fill the relabelled set with states no policy visits)")
    batch_size: int = _field(128, "TD3's minibatch size")
    buffer_size: int = _field(200_000, "replay buffer capacity (transitions)")
    learning_rate: float = _field(1e-3, "TD3's learning rate (actor and critics)")
    action_noise: float = _field(0.1, "standard deviation of TD3's Gaussian exploration noise")
    q_weight: float = _field(0.1, "weight of the critic's term -Q(s, pi(s)) / max(mean |Q|, 1) in the "
                                  "actor's loss (TD3's own actor loss is this term alone)")
    bc_weight: float = _field(20.0, "weight of the behaviour-cloning term on the demonstrations in the "
                                    "actor's loss (0: TD3's actor loss alone)")
    bc_batch: int = _field(64, "demonstration transitions per update for the behaviour-cloning term")
    bc_pretrain: int = _field(2000, "gradient updates on the demonstrations alone before the agent first "
                                    "acts: the actor by behaviour cloning only, the critics by TD learning")
    expert_relabel: int = _field(1, "1: every state the agent visits is labelled with the scripted expert's "
                                    "action on the true state, and the behaviour-cloning term imitates these "
                                    "labels as well as the demonstrations (DAgger, Ross et al. 2011); 0: the "
                                    "demonstrations only")
    q_filter: int = _field(0, "1: the behaviour-cloning term counts only where the critic rates the "
                              "demonstrated action above the policy's; 0: everywhere")
    run: str | None = _field(None, "an s3k run whose detector gives the keypoint observations from four "
                                   "rendered views (default: ground-truth keypoints); the reward always "
                                   "uses the environment's keypoints")
    image_size: int = _field(64, "width and height of the rendered views (detector and beta-VAE)")
    vae_latent: int = _field(10, "beta-VAE latent size")
    vae_beta: float = _field(4.0, "beta-VAE's beta (weight of the KL term)")
    vae_images: int = _field(2000, "unlabelled frames of the environment the beta-VAE is trained on")
    vae_steps: int = _field(3000, "beta-VAE training steps")
    threads: int = _field(1, "torch threads (the networks are small: one thread is fastest, and several "
                             "runs can share the machine)")

    def __post_init__(self) -> None:
        if self.agent not in AGENTS:
            raise UserError(f"agent (--agent): must be one of {', '.join(AGENTS)}, got {self.agent!r}")
        for name in ("steps", "checkpoint_every", "batch_size", "buffer_size", "image_size"):
            if getattr(self, name) < 1:
                raise UserError(f"{name} (--{name.replace('_', '-')}): must be >= 1, "
                                f"got {getattr(self, name)}")
        for name in ("demos", "eval_episodes", "learning_starts", "eval_every"):
            if getattr(self, name) < 0:
                raise UserError(f"{name} (--{name.replace('_', '-')}): must be >= 0, "
                                f"got {getattr(self, name)}")

    def identity(self) -> dict:
        """What a resumed run must share with the one it continues (everything but ``steps``)."""
        d = dataclasses.asdict(self)
        d.pop("steps")
        d.pop("eval_episodes")
        d.pop("eval_every")
        d.pop("threads")
        return d


def saved_config(config_file: Path) -> dict:
    """A run's ``config.json`` as :class:`AgentConfig` fields; a run begun before expert relabelling existed
    imitated its demonstrations only, so its missing ``expert_relabel`` is 0."""
    return {"expert_relabel": 0, **json.loads(Path(config_file).read_text())}


def td3_with_demonstrations():
    """TD3 whose actor also imitates the demonstrations (DDPG from demonstrations, Nair et al. 2018; the
    Q-term normalized as in TD3+BC, Fujimoto and Gu 2021).

    The actor's loss is ``q_weight * -Q(s, pi(s)) / max(mean|Q|, 1)`` on a replay minibatch plus ``bc_weight``
    times the squared action error ``|pi(s_d) - a_d|^2`` on a minibatch of demonstration transitions, or, with
    :attr:`expert_actions` set (``expert_relabel``), of all the buffer's transitions, each with the scripted
    expert's action on the true state it was in (DAgger's aggregate, Ross et al. 2011); with
    ``q_filter`` the latter counts only where ``Q(s_d, a_d) > Q(s_d, pi(s_d))``. The critics learn as in TD3
    from the whole buffer, demonstrations included. :meth:`pretrain` first fits the actor to the
    demonstrations alone (the Q-term off) while the critics learn their values. Built on first use so that
    importing s3k does not import Stable-Baselines3.

    What each part does on the insertion task (``benchmarks/robot.py --agent-ablation``, docs/robot.md):
    TD3 with the demonstrations only in its buffer does not succeed once in 4000 steps; cloning the
    demonstrations inserts at once, but imitating them alone the acting policy drifts to states they never
    show and fails there; with the visited states relabelled it stays near the expert whatever the Q-term's
    weight.
    """
    from stable_baselines3 import TD3
    from stable_baselines3.common.utils import polyak_update

    class TD3Demonstrations(TD3):
        demo_obs: th.Tensor | None = None
        demo_actions: th.Tensor | None = None
        bc_weight: float = 0.0
        bc_batch: int = 64
        q_filter: bool = False
        q_weight: float = 1.0
        # The expert's action for each replay-buffer transition (the demonstrated one for a demonstration),
        # when the states the agent visits are relabelled; None when only the demonstrations are imitated.
        expert_actions: np.ndarray | None = None

        def _store_transition(self, replay_buffer, buffer_action, new_obs, reward, dones, infos) -> None:
            if self.expert_actions is not None:
                self.expert_actions[replay_buffer.pos] = infos[0]["expert_action"]
            super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

        def _imitation_batch(self) -> tuple[th.Tensor, th.Tensor] | None:
            """States and the actions to imitate there: from the relabelled buffer, or the demonstrations."""
            rb = self.replay_buffer
            if self.expert_actions is not None and rb is not None and rb.pos > 0:
                rows = th.randint(rb.pos, (self.bc_batch,)).numpy()  # the buffer never wraps round
                return (th.as_tensor(rb.observations[rows, 0], dtype=th.float32),
                        th.as_tensor(self.expert_actions[rows], dtype=th.float32))
            if self.demo_obs is None or self.demo_actions is None or len(self.demo_obs) == 0:
                return None
            idx = th.randint(len(self.demo_obs), (self.bc_batch,))
            return self.demo_obs[idx], self.demo_actions[idx]

        def pretrain(self, updates: int, batch_size: int) -> None:
            """``updates`` updates from the buffer as it is (the demonstrations), the actor's Q-term off."""
            q_weight, self.q_weight = self.q_weight, 0.0
            try:
                self.train(updates, batch_size)
            finally:
                self.q_weight = q_weight

        def set_demonstrations(self, obs: np.ndarray, actions: np.ndarray, weight: float, batch: int,
                               q_filter: bool = False, q_weight: float = 1.0) -> None:
            """Demonstration transitions ``obs (N, D)``, ``actions (N, 6)`` (the policy's action scale), and
            the weights of the actor's two terms."""
            self.demo_obs = th.as_tensor(obs, dtype=th.float32)
            self.demo_actions = th.as_tensor(actions, dtype=th.float32)
            self.bc_weight, self.bc_batch, self.q_filter, self.q_weight = weight, batch, q_filter, q_weight

        def train(self, gradient_steps: int, batch_size: int = 100) -> None:
            self.policy.set_training_mode(True)
            if getattr(self, "_logger", None) is not None:  # no logger before learn(): the pretraining
                self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
            assert self.replay_buffer is not None
            for _ in range(gradient_steps):
                self._n_updates += 1
                batch = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
                with th.no_grad():
                    noise = th.randn_like(batch.actions) * self.target_policy_noise
                    noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                    next_a = (self.actor_target(batch.next_observations) + noise).clamp(-1, 1)
                    next_q = th.cat(self.critic_target(batch.next_observations, next_a), dim=1)
                    next_q = next_q.min(dim=1, keepdim=True)[0]
                    target = batch.rewards + (1 - batch.dones) * self.gamma * next_q
                qs = self.critic(batch.observations, batch.actions)
                critic_loss = th.stack([F.mse_loss(q, target) for q in qs]).sum()
                self.critic.optimizer.zero_grad()
                critic_loss.backward()
                self.critic.optimizer.step()
                if self._n_updates % self.policy_delay:
                    continue
                q_pi = self.critic.q1_forward(batch.observations, self.actor(batch.observations))
                actor_loss = -self.q_weight * q_pi.mean() / q_pi.abs().mean().detach().clamp_min(1.0)
                imitate = self._imitation_batch() if self.bc_weight > 0 else None
                if imitate is not None:
                    s_d, a_d = imitate
                    pi_d = self.actor(s_d)
                    better = th.ones(len(s_d), 1)
                    if self.q_filter:
                        with th.no_grad():
                            q_demo = self.critic.q1_forward(s_d, a_d)
                            better = (q_demo > self.critic.q1_forward(s_d, pi_d)).float()
                    bc = (((pi_d - a_d) ** 2).sum(-1, keepdim=True) * better).mean()
                    actor_loss = actor_loss + self.bc_weight * bc
                self.actor.optimizer.zero_grad()
                actor_loss.backward()
                self.actor.optimizer.step()
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
                polyak_update(self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0)
                polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)

    return TD3Demonstrations


def make_env(cfg: AgentConfig, vae=None, detector=None, training: bool = True) -> gym.Env:
    """The environment an agent of ``cfg`` sees (the beta-VAE agent's wraps the views' latent); ``detector``
    (stateless) may be shared between environments, else ``cfg.run``'s is loaded. Only a ``training`` one
    labels its steps with the expert's action (``cfg.expert_relabel``); an evaluation needs no labels."""
    if detector is None and cfg.run is not None:
        detector = RunDetector(cfg.run, KEYPOINTS)
        if detector.image_size != (cfg.image_size, cfg.image_size):
            raise UserError(f"image_size (--image-size): run {cfg.run} reads {detector.image_size[0]} x "
                            f"{detector.image_size[1]} px views, the agent renders {cfg.image_size} px",
                            hint=f"give --image-size {detector.image_size[0]}")
    env: gym.Env = InsertionEnv(detector=detector, image_size=cfg.image_size, camera_seed=0,
                                expert_labels=training and bool(cfg.expert_relabel))
    if cfg.agent == "beta_vae":
        from s3k.robot.beta_vae import LatentObservation

        env = LatentObservation(env, vae)
    return env


def _state_obs(env: gym.Env, obs: np.ndarray) -> np.ndarray:
    """The keypoint observation the demonstrator reads (the beta-VAE wrapper keeps it aside)."""
    last = getattr(env, "last_state", None)
    return obs if last is None else last


def collect_images(cfg: AgentConfig, n: int, seed: int) -> np.ndarray:
    """``n`` unlabelled frames ``uint8 (n, 4, S, S, 3)`` of the environment, under the demonstrator with
    noise (so they cover the states an agent visits)."""
    env = InsertionEnv(image_size=cfg.image_size)
    rng = np.random.default_rng(seed)
    frames: list[np.ndarray] = []
    obs, _ = env.reset(seed=seed)
    while len(frames) < n:
        frames.append(env.views()[0])
        action = scripted_action(obs) + rng.normal(0.0, 0.5, 6)
        obs, _, term, trunc, _ = env.step(np.clip(action, -1, 1))
        if term or trunc:
            obs, _ = env.reset(seed=int(rng.integers(1 << 31)))
    env.close()
    return np.stack(frames)


def add_demonstrations(model, env: gym.Env, episodes: int, seed: int) -> int:
    """Runs the scripted demonstrator for ``episodes`` and adds its transitions to ``model``'s replay
    buffer; returns how many."""
    n = 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed * 100_003 + ep)
        done = False
        while not done:
            action = scripted_action(_state_obs(env, obs))
            next_obs, reward, term, trunc, info = env.step(action)
            done = term or trunc
            if getattr(model, "expert_actions", None) is not None:
                model.expert_actions[model.replay_buffer.pos] = action
            model.replay_buffer.add(obs[None], next_obs[None], action[None], np.array([reward]),
                                    np.array([done]), [{**info, "TimeLimit.truncated": trunc and not term}])
            obs = next_obs
            n += 1
    return n


def evaluate_agent(model, env: gym.Env, episodes: int, seed: int) -> dict:
    """Success rate of the deterministic policy over ``episodes`` (fixed seeds, so evaluations compare)."""
    successes, true_successes, returns = 0, 0, []
    for ep in range(episodes):
        obs, _ = env.reset(seed=10_000_000 + seed * 1000 + ep)
        done, ret = False, 0.0
        info: dict = {}
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, term, trunc, info = env.step(action)
            ret += float(reward)
            done = term or trunc
        successes += bool(info.get("is_success"))
        true_successes += bool(info.get("true_success"))
        returns.append(ret)
    n = max(episodes, 1)
    return {"success_rate": successes / n, "true_success_rate": true_successes / n,
            "mean_return": float(np.mean(returns)) if returns else None, "episodes": episodes}


# ---------------------------------------------------------------------------------------------- training
def train_agent(out: str | Path, cfg: AgentConfig, resume: bool = False,
                log: Callable[[str], None] = say) -> dict:
    """Trains (or with ``resume`` continues) the agent of ``cfg`` in run folder ``out``.

    Returns the final evaluation: ``{"agent", "seed", "env_steps", "success_rate", "true_success_rate",
    "mean_return", "episodes", "demonstration_steps", "wall_time_s", "cpu_seconds"}`` (``progress.json``'s
    ``final``; its ``evaluations`` hold the curve, one every ``eval_every`` steps). ``cpu_seconds`` is the
    process CPU time of the run over all its resumptions, the beta-VAE's training included.
    """
    from stable_baselines3.common.noise import NormalActionNoise

    out = Path(out)
    ckpt = out / "checkpoint"
    config_file = out / "config.json"
    if resume:
        if not config_file.is_file():
            raise UserError(f"{out}: no agent run to resume (no config.json)",
                            hint="drop --resume to start one")
        old = AgentConfig(**saved_config(config_file))
        if old.identity() != cfg.identity():
            diff = sorted(k for k, v in cfg.identity().items() if old.identity().get(k) != v)
            raise UserError(f"{out}: --resume with other settings than the run's ({', '.join(diff)})",
                            hint="give the run's settings or a new --out")
    elif out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: exists and is not empty", hint="pass --resume to continue it or a new --out")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(dataclasses.asdict(cfg), config_file)
    t0, c0 = time.perf_counter(), time.process_time()
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    vae = None
    if cfg.agent == "beta_vae":
        from s3k.robot.beta_vae import load_vae, save_vae, train_beta_vae

        if (out / "vae.pt").is_file():
            vae = load_vae(out / "vae.pt")
        else:
            log(f"beta-VAE: collecting {cfg.vae_images} unlabelled frames of the environment")
            images = collect_images(cfg, cfg.vae_images, cfg.seed)
            vae = train_beta_vae(images, cfg.vae_latent, cfg.vae_beta, cfg.vae_steps, seed=cfg.seed,
                                 log=lambda s, loss, p: log(f"beta-VAE step {s}: loss {loss:.1f}"))
            save_vae(vae, out / "vae.pt", cfg.vae_beta)
    env = make_env(cfg, vae)
    detector = getattr(env.unwrapped, "detector", None)  # shared with the evaluation environment
    env.reset(seed=cfg.seed)
    noise = NormalActionNoise(np.zeros(6), cfg.action_noise * np.ones(6))
    agent_class = td3_with_demonstrations()
    model = agent_class("MlpPolicy", env, learning_rate=cfg.learning_rate, buffer_size=cfg.buffer_size,
                learning_starts=cfg.learning_starts, batch_size=cfg.batch_size, action_noise=noise,
                seed=cfg.seed, device="cpu", verbose=0)
    if cfg.expert_relabel:
        model.expert_actions = np.zeros((cfg.buffer_size, 6), np.float32)
    progress_file = out / "progress.json"
    progress: dict = {"evaluations": []}
    if resume and progress_file.is_file():
        progress = json.loads(progress_file.read_text())
    found = checkpoint_folder(ckpt) if resume else None
    if found is not None:
        state = load_checkpoint(model, found)
        held = model.replay_buffer.pos if model.replay_buffer is not None else 0
        log(f"resumed at {state['env_steps']} environment steps ({held} transitions)")
    else:
        demo_steps = add_demonstrations(model, env, cfg.demos, cfg.seed)
        state = {"env_steps": 0, "updates": 0, "episodes": 0, "demonstration_steps": demo_steps}
        log(f"{cfg.demos} demonstrations: {demo_steps} transitions in the replay buffer")
    # The demonstrations are the buffer's first transitions (it never wraps round: buffer_size > steps).
    n_demo = int(state.get("demonstration_steps", 0))
    if n_demo + cfg.steps > cfg.buffer_size:
        raise UserError(f"buffer_size (--buffer-size): {cfg.buffer_size} transitions cannot hold the "
                        f"{n_demo} demonstration steps and --steps {cfg.steps}",
                        hint=f"start a run with --buffer-size {n_demo + cfg.steps} or more")
    rb = model.replay_buffer
    model.set_demonstrations(rb.observations[:n_demo, 0], rb.actions[:n_demo, 0], cfg.bc_weight,
                             cfg.bc_batch, bool(cfg.q_filter), cfg.q_weight)
    cpu_before = float(state.get("cpu_seconds", 0.0))  # this process's CPU time adds to the earlier runs'
    # Evaluations on an environment of their own, so that the training episode in progress is not disturbed.
    eval_env = make_env(cfg, vae, detector, training=False)

    def evaluate_at(steps: int) -> dict:
        """The deterministic policy's evaluation, appended to the curve."""
        result = evaluate_agent(model, eval_env, cfg.eval_episodes, cfg.seed)
        result.update(agent=cfg.agent, seed=cfg.seed, env_steps=steps)
        progress["evaluations"].append(result)
        log(f"evaluation at {steps} environment steps: success rate {result['success_rate']:.2f}")
        return result

    if found is None:
        if cfg.bc_pretrain and n_demo:
            model.pretrain(cfg.bc_pretrain, cfg.batch_size)
        evaluate_at(0)
    # Stable-Baselines3 makes a logger of its own on every learn() call, each with a new empty folder in the
    # temporary directory; the run's record is progress.json, so its logger writes nowhere.
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))
    eval_every = cfg.eval_every or cfg.checkpoint_every
    done_steps = int(model.num_timesteps)
    # A resumed run keeps the evaluations up to its checkpoint (later ones were of a policy now lost).
    progress["evaluations"] = [e for e in progress["evaluations"] if e["env_steps"] <= done_steps]
    result: dict | None = None
    while model.num_timesteps < cfg.steps:
        now = int(model.num_timesteps)
        chunk = min(cfg.checkpoint_every - now % cfg.checkpoint_every, eval_every - now % eval_every,
                    cfg.steps - now)
        model.learn(total_timesteps=chunk, reset_num_timesteps=False, log_interval=1_000_000)
        now = int(model.num_timesteps)
        if now % eval_every == 0 or now >= cfg.steps:
            result = evaluate_at(now)
        if now % cfg.checkpoint_every == 0 or now >= cfg.steps:
            state.update(env_steps=now, updates=int(model._n_updates), episodes=int(model._episode_num),
                         cpu_seconds=cpu_before + time.process_time() - c0)
            save_checkpoint(model, ckpt, state)
            atomic_write_json(progress, progress_file)
            log(f"checkpoint at {now} environment steps")
    if result is None or result["env_steps"] != int(model.num_timesteps):  # resumed at or past --steps
        result = evaluate_at(int(model.num_timesteps))
    result.update(demonstration_steps=int(state.get("demonstration_steps", 0)),
                  wall_time_s=time.perf_counter() - t0, cpu_seconds=cpu_before + time.process_time() - c0)
    progress["final"] = result
    atomic_write_json(progress, progress_file)
    env.close()
    eval_env.close()
    return result
