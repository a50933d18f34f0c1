"""Tests of the cable-insertion environment and its agents (s3k/robot/insertion_env.py, agents.py,
beta_vae.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from s3k.base.errors import UserError  # noqa: E402
from s3k.robot.insertion_env import (  # noqa: E402
    SUCCESS_DISTANCE,
    InsertionEnv,
    scripted_action,
)


def test_insertion_env_passes_gymnasium_check_env():
    env = InsertionEnv()
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert obs.shape == (24,) and obs.dtype == np.float32
    np.testing.assert_allclose(obs[15:24].reshape(3, 3), env.true_keypoints(), atol=1e-6)


def test_demonstrator_inserts_the_plug_and_the_tip_label_moves_to_the_opening():
    env = InsertionEnv()
    obs, _ = env.reset(seed=1)
    assert env.distance() > 0.05
    total, steps, info = 0.0, 0, {}
    done = False
    while not done:
        obs, reward, term, trunc, info = env.step(scripted_action(obs))
        total += reward
        steps += 1
        done = term or trunc
    assert info["is_success"] and info["true_success"] and steps < env.max_steps
    assert info["distance"] < SUCCESS_DISTANCE
    tip_site = env.data.site_xpos[env._sites[0]]
    socket = env.true_keypoints()[2]
    assert tip_site[2] < socket[2] - 0.01  # the real tip is inside the hole...
    np.testing.assert_allclose(env.true_keypoints()[0], socket)  # ...its label is at the opening
    assert total > env.max_steps - steps  # finishing early is paid for the steps left


def test_gripper_that_strays_ends_the_episode():
    env = InsertionEnv()
    env.reset(seed=0)
    done, info, steps = False, {}, 0
    while not done:
        _, _, term, trunc, info = env.step(np.array([0, 0, 1, 0, 0, 0], np.float32))
        steps += 1
        done = term or trunc
    assert info["strayed"] and not info["is_success"] and steps < env.max_steps


def test_detector_callable_gives_the_keypoint_observations():
    calls = []

    def detector(images, K, R, t):
        calls.append(images.shape)
        X = env.true_keypoints() + 0.01
        valid = np.array([True, len(calls) < 3, True])  # plug_base goes missing after two frames
        return X, valid

    env = InsertionEnv(detector=detector, image_size=32)
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(obs[15:24].reshape(3, 3), env.true_keypoints() + 0.01, atol=1e-5)
    obs, *_ = env.step(np.zeros(6, np.float32))
    obs, *_ = env.step(np.zeros(6, np.float32))
    kp = obs[15:24].reshape(3, 3)
    np.testing.assert_allclose(kp[[0, 2]], env.true_keypoints()[[0, 2]] + 0.01, atol=1e-5)
    assert calls[0] == (4, 32, 32, 3)
    assert np.all(np.isfinite(kp[1]))  # the missed keypoint keeps its last value


def test_a_run_from_before_expert_relabelling_resumes_as_it_was(tmp_path):
    """A run whose config.json has no ``expert_relabel`` imitated its demonstrations only: ``--resume``
    with no options continues it so, and its replay buffer (no expert labels in it) loads."""
    from s3k.cli import main

    out = tmp_path / "old"
    options = ["--steps", "8", "--demos", "1", "--checkpoint-every", "4", "--eval-episodes", "1",
               "--batch-size", "8", "--buffer-size", "200", "--bc-pretrain", "2", "--learning-starts", "100"]
    assert main(["robot", "train-agent", "--out", str(out), *options, "--expert-relabel", "0"]) == 0
    config = json.loads((out / "config.json").read_text())
    del config["expert_relabel"]
    (out / "config.json").write_text(json.dumps(config))
    with np.load(out / "checkpoint" / "replay.npz") as z:
        assert "expert_actions" not in z.files
    assert main(["robot", "train-agent", "--out", str(out), "--resume", "--steps", "12"]) == 0
    assert json.loads((out / "config.json").read_text())["expert_relabel"] == 0
    assert json.loads((out / "checkpoint" / "state.json").read_text())["env_steps"] == 12


def test_expert_label_is_the_demonstrator_on_the_true_state_the_step_started_from():
    def detector(images, K, R, t):  # sees every keypoint 3 cm off
        return env.true_keypoints() + np.array([0.03, 0.0, 0.0]), np.ones(3, bool)

    env = InsertionEnv(detector=detector, image_size=16, expert_labels=True)
    obs, _ = env.reset(seed=3)
    for _ in range(3):
        state = env.state_observation()
        np.testing.assert_allclose(state[15:].reshape(3, 3), env.true_keypoints(), atol=1e-6)
        np.testing.assert_allclose(obs[15:].reshape(3, 3), env.true_keypoints() + [0.03, 0, 0], atol=1e-6)
        obs, _, _, _, info = env.step(np.full(6, 0.3, np.float32))
        np.testing.assert_allclose(info["expert_action"], scripted_action(state), atol=1e-6)
    assert "expert_action" not in InsertionEnv().step(np.zeros(6, np.float32))[4]


def test_td3_agent_with_demonstrations_checkpoints_and_resumes(tmp_path, monkeypatch):
    import tempfile

    import torch

    from s3k.robot.agent_checkpoint import load_checkpoint
    from s3k.robot.agents import AgentConfig, train_agent

    out = tmp_path / "agent"
    cfg = AgentConfig(steps=30, demos=1, checkpoint_every=15, eval_episodes=1, learning_starts=5,
                      batch_size=16, buffer_size=500, bc_pretrain=10)
    scratch = tmp_path / "tmp"  # the temporary directory, to see that the training leaves nothing there
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    monkeypatch.delenv("SB3_LOGDIR", raising=False)

    def killed_after_first_checkpoint(line: str) -> None:
        if line.startswith("checkpoint at 15"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # a run killed after its first checkpoint...
        train_agent(out, cfg, log=killed_after_first_checkpoint)
    assert json.loads((out / "checkpoint" / "state.json").read_text())["env_steps"] == 15
    # The curve so far is saved with the checkpoint: one evaluation at 15 steps, no final one yet.
    progress = json.loads((out / "progress.json").read_text())
    assert [e["env_steps"] for e in progress["evaluations"]] == [0, 15] and "final" not in progress
    log: list[str] = []
    first = train_agent(out, cfg, resume=True, log=log.append)  # ...resumes from it
    assert any("resumed at 15" in line for line in log)
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert first["env_steps"] == 30 and state["env_steps"] == 30 and state["updates"] > 0
    assert not list(scratch.glob("SB3-*"))  # no logger folder per learn() call
    demo = state["demonstration_steps"]
    assert demo > 0
    saved = torch.load(out / "checkpoint" / "agent.pt", weights_only=True)

    with pytest.raises(UserError, match="exists"):
        train_agent(out, cfg, log=lambda s: None)
    with pytest.raises(UserError, match="batch_size"):
        train_agent(out, AgentConfig(**{**cfg.__dict__, "batch_size": 8}), resume=True, log=lambda s: None)

    # The checkpoint restores the policy exactly and the whole replay buffer.
    from stable_baselines3 import TD3

    from s3k.robot.agents import make_env

    model = TD3("MlpPolicy", make_env(cfg), buffer_size=500, device="cpu")
    load_checkpoint(model, out / "checkpoint")
    for k, v in saved["policy"].items():
        torch.testing.assert_close(model.policy.state_dict()[k], v)
    assert model.replay_buffer.pos == demo + 30 and model.num_timesteps == 30

    log.clear()
    second = train_agent(out, AgentConfig(**{**cfg.__dict__, "steps": 45}), resume=True, log=log.append)
    assert any("resumed at 30" in line for line in log)
    assert second["env_steps"] == 45
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert state["env_steps"] == 45
    with np.load(out / "checkpoint" / "replay.npz", allow_pickle=False) as z:
        assert len(z["actions"]) == demo + 45
        # Every transition, the agent's own and the resumed run's too, carries the expert's action for its
        # state; on ground-truth keypoints the observation is that state, so the label is the demonstrator's
        # action on it (for a demonstration, what was done).
        labels = np.stack([scripted_action(o) for o in z["observations"][:, 0]])
        np.testing.assert_allclose(z["expert_actions"], labels, atol=1e-6)
        np.testing.assert_allclose(z["expert_actions"][:demo], z["actions"][:demo, 0], atol=1e-6)
        assert not np.allclose(z["expert_actions"][demo:], z["actions"][demo:, 0], atol=1e-3)
    progress = json.loads((out / "progress.json").read_text())
    # One evaluation per checkpoint, none repeated across the resumptions; the final one is the last.
    assert [e["env_steps"] for e in progress["evaluations"]] == [0, 15, 30, 45]
    assert progress["final"]["env_steps"] == 45 and progress["final"]["cpu_seconds"] > 0


def test_checkpoint_survives_a_kill_between_its_renames(tmp_path):
    from s3k.robot.agent_checkpoint import checkpoint_folder

    ckpt = tmp_path / "checkpoint"
    assert checkpoint_folder(ckpt) is None
    old = tmp_path / "checkpoint.old"
    old.mkdir()
    (old / "state.json").write_text("{}")
    assert checkpoint_folder(ckpt) == old  # the previous checkpoint had moved aside, the new not yet in
    ckpt.mkdir()
    (ckpt / "state.json").write_text("{}")
    assert checkpoint_folder(ckpt) == ckpt


def test_beta_vae_learns_and_feeds_the_latent_observation():
    import torch

    from s3k.robot.beta_vae import BetaVAE, LatentObservation, train_beta_vae, views_to_tensor

    rng = np.random.default_rng(0)
    images = np.zeros((16, 4, 16, 16, 3), np.uint8)
    for i in range(16):  # a bright square at a random place: something to encode
        y, x = rng.integers(0, 10, 2)
        images[i, :, y:y + 6, x:x + 6] = 220
    vae = BetaVAE(latent=10, size=16)
    x = views_to_tensor(images)
    assert x.shape == (16, 12, 16, 16)
    torch.manual_seed(0)
    before = float(vae.loss(x, beta=4.0)[0].detach())
    trained = train_beta_vae(images, latent=10, beta=4.0, steps=60, batch_size=8, seed=0)
    torch.manual_seed(0)
    after = float(trained.loss(x, beta=4.0)[0].detach())
    assert after < 0.8 * before

    env = LatentObservation(InsertionEnv(image_size=16), trained)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (25,) and env.observation_space.contains(obs)
    assert env.last_state is not None and env.last_state.shape == (24,)


@pytest.mark.slow
def test_beta_vae_agent_trains_a_few_steps(tmp_path):
    from s3k.robot.agents import AgentConfig, train_agent

    cfg = AgentConfig(agent="beta_vae", steps=10, demos=1, checkpoint_every=5, eval_episodes=1,
                      learning_starts=2, batch_size=8, buffer_size=200, vae_images=16, vae_steps=5,
                      image_size=32, bc_pretrain=5)
    result = train_agent(tmp_path / "vae", cfg, log=lambda s: None)
    assert result["env_steps"] == 10 and (tmp_path / "vae" / "vae.pt").is_file()


def test_insertion_dataset_labels_are_the_keypoints_projections(tmp_path):
    from s3k.cli import main
    from s3k.data import Dataset, usable_labels
    from s3k.robot.insertion_env import KEYPOINTS
    from s3k.sim.camera import project_points

    out = tmp_path / "insertion"
    assert main(["robot", "simulate-insertion", "--out", str(out), "--size", "32", "--labelled", "3",
                 "--unlabelled", "6", "--test", "2", "--no-progress"]) == 0
    ds = Dataset.open(out)
    assert ds.keypoints == KEYPOINTS and ds.static_calibration
    assert (len(ds.frames("labelled")), len(ds.frames("unlabelled")), len(ds.frames("test"))) == (3, 6, 2)
    # The rig is the environment's: an agent's detector sees the same cameras.
    env = InsertionEnv(image_size=32)
    env.reset(seed=0)
    _, K, R, t = env.views()
    rig = ds.rig().numpy()
    np.testing.assert_allclose(rig["R"], R, atol=1e-6)
    np.testing.assert_allclose(rig["K"], K, atol=1e-4)
    ids = ds.frames("labelled")
    uv, mask = ds.labels(ids)
    X, _ = ds.points3d(ids)
    for b in range(len(ids)):
        proj, _ = project_points(K, R, t, np.asarray(X[b], dtype=np.float64))
        np.testing.assert_allclose(np.asarray(uv[b])[mask[b]], proj[mask[b]], atol=1e-3)
    assert usable_labels(ds, "labelled").all()


def test_pretraining_fits_the_actor_to_the_demonstrations_and_the_q_term_can_be_switched_off():
    """The demonstration agent's pretraining is behaviour cloning: the actor's error on the demonstrated
    actions falls; with bc_weight 0 and the Q-term off the actor does not move at all."""
    import torch

    from s3k.robot.agents import AgentConfig, add_demonstrations, make_env, td3_with_demonstrations

    torch.manual_seed(0)
    cfg = AgentConfig(demos=2, buffer_size=500, batch_size=32)
    env = make_env(cfg)
    model = td3_with_demonstrations()("MlpPolicy", env, buffer_size=500, batch_size=32, seed=0, device="cpu")
    n = add_demonstrations(model, env, cfg.demos, seed=0)
    obs = model.replay_buffer.observations[:n, 0]
    acts = model.replay_buffer.actions[:n, 0]

    def error() -> float:
        with torch.no_grad():
            return float(((model.actor(torch.as_tensor(obs)) - torch.as_tensor(acts)) ** 2).sum(-1).mean())

    model.set_demonstrations(obs, acts, weight=0.0, batch=16, q_weight=1.0)
    frozen = {k: v.clone() for k, v in model.actor.state_dict().items()}
    model.pretrain(20, 32)  # Q-term off during pretraining, no BC: the actor is untouched
    for k, v in model.actor.state_dict().items():
        torch.testing.assert_close(v, frozen[k])
    assert model.q_weight == 1.0  # restored after pretraining
    before = error()
    model.set_demonstrations(obs, acts, weight=20.0, batch=16, q_weight=1.0)
    model.pretrain(300, 32)
    assert error() < 0.3 * before
    env.close()
