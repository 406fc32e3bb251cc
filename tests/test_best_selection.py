"""Which evaluation a training run keeps in ``best/`` (``select_best``), and what a sweep reports
as a run's best evaluation."""

from __future__ import annotations

import json

import pytest

import uwdock.rl.train.session as session_mod
from uwdock.dockcore.config import ConfigError, from_dict, replace
from uwdock.rl.policy.policy_format import policy_files
from uwdock.rl.train.session import TrainingSession, eval_score, replaces_best
from uwdock.rl.train.sweep import _trial_summary
from uwdock.rl.train.training import TrainConfig

# The eight 30-episode evaluations of a gentle-landing stage 2 (near-seat recipe, seed 2:
# bench/results/scratch_runs/realistic_near_gentle_s2 in the tag lab-notebook-2026-12): (step,
# strict, paper, mean return, collisions per episode). One more episode docked at the first
# evaluation; the collisions fall to 0.97 by the last.
STAGE2 = [
    (28672, 1.0, 1.0, 100.2, 2.47),
    (53248, 0.9667, 0.9667, 56.1, 2.43),
    (77824, 0.9667, 0.9667, 112.4, 1.93),
    (102400, 0.9667, 0.9667, 91.9, 2.1),
    (126976, 0.9667, 0.9667, 121.6, 1.8),
    (151552, 0.9667, 0.9667, 181.2, 1.23),
    (176128, 0.9667, 0.9667, 153.0, 1.53),
    (200704, 0.9667, 0.9667, 214.9, 0.97),
]


# The seventeen evaluations of a shipped-recipe run (configs/realistic/policy.toml, seed 6,
# trained under "return"): (step, strict, mean time to dock s). Every evaluation docked 29 or
# 30 of 30; "return" kept 253952 (30 of 30, 10.67 s), which held out at 0.77x the PID's time.
RECIPE_SEED6 = [
    (0, 0.9667, 12.01), (28672, 0.9667, 12.01), (53248, 0.9667, 12.01), (77824, 0.9667, 11.15),
    (102400, 1.0, 11.01), (126976, 1.0, 10.89), (151552, 1.0, 10.83), (176128, 1.0, 10.62),
    (200704, 1.0, 10.28), (225280, 1.0, 10.67), (253952, 1.0, 10.67), (278528, 0.9667, 10.11),
    (303104, 0.9667, 10.2), (327680, 0.9667, 10.12), (352256, 0.9667, 9.53),
    (376832, 0.9667, 9.55), (401408, 0.9667, 9.43),
]  # fmt: skip


def _summary(strict, paper, ret, coll, time_s=9.0):
    return {
        "episodes": 30,
        "success_rate": paper,
        "success_rate_strict": strict,
        "mean_return": ret,
        "mean_collisions": coll,
        "mean_time_to_dock_s": time_s,
    }


def _kept(rows, rule):
    """The step ``rule`` keeps over ``rows`` of summaries, evaluated one after another."""
    history, kept = [], None
    for step, summary in rows:
        record = {"step": step, **summary}
        if replaces_best(summary, kept, history, "strict", rule):
            kept = record
        history.append(record)
    return kept["step"]


def test_fastest_keeps_the_quickest_evaluation_within_one_episode_of_the_best():
    rows = [(step, _summary(s, s, 0.0, 0.0, t)) for step, s, t in RECIPE_SEED6]
    assert _kept(rows, "fastest") == 401408  # 29 of 30, 9.43 s
    assert _kept(rows, "success") == 102400  # the first 30 of 30
    # two episodes short of the best is out of reach, however fast
    slow_best = [(0, _summary(1.0, 1.0, 0, 0, 12.0)), (1, _summary(0.9333, 0.9333, 0, 0, 8.0))]
    assert _kept(slow_best, "fastest") == 0
    # a rate rising more than one episode above the kept one takes best/, even if slower
    rising = [
        (0, _summary(0.9, 0.9, 0, 0, 8.0)),
        (1, _summary(0.9333, 0.9333, 0, 0, 7.0)),
        (2, _summary(1.0, 1.0, 0, 0, 11.0)),
        (3, _summary(0.9667, 0.9667, 0, 0, 10.0)),
    ]
    assert _kept(rising, "fastest") == 3
    # nothing docked: no time, never faster than an evaluation that docked
    none = [(0, _summary(0.0, 0.0, 0, 0, None)), (1, _summary(0.0, 0.0, 0, 0, 30.0))]
    assert _kept(none, "fastest") == 1


def test_eval_score_ranks_success_first_or_the_return_alone():
    a, b = _summary(1.0, 1.0, 100.2, 2.47), _summary(0.9667, 0.9667, 214.9, 0.97)
    assert eval_score(a, "strict", "success") > eval_score(b, "strict", "success")
    assert eval_score(a, "strict", "return") < eval_score(b, "strict", "return")
    # success: the rate that ends the episode ranks first
    strict_first = _summary(0.9, 0.9, 0.0, 0.0)
    paper_first = _summary(0.8, 1.0, 0.0, 0.0)
    assert eval_score(strict_first, "strict", "success") > eval_score(
        paper_first, "strict", "success"
    )
    assert eval_score(strict_first, "paper", "success") < eval_score(
        paper_first, "paper", "success"
    )


def test_select_best_is_checked_when_a_config_is_read():
    assert from_dict(TrainConfig, {"select_best": "return"}).select_best == "return"
    assert from_dict(TrainConfig, {"select_best": "fastest"}).select_best == "fastest"
    with pytest.raises(ConfigError, match="select_best"):
        from_dict(TrainConfig, {"select_best": "collisions"})


@pytest.mark.parametrize(
    ("select_best", "kept_step"), [("success", 28672), ("return", 200704), ("fastest", 200704)]
)
def test_the_session_keeps_the_selected_evaluation_in_best(
    tmp_path, monkeypatch, select_best, kept_step
):
    """A real PPO model whose weights change before every evaluation: best/ holds the
    model as it was at the kept evaluation, the history flags it last, and a sweep's summary
    of the run reports that evaluation."""
    from stable_baselines3 import PPO

    summaries = iter(_summary(*row[1:], 12.0 - i) for i, row in enumerate(STAGE2))
    monkeypatch.setattr(session_mod, "summarise", lambda rows: next(summaries))
    cfg = replace(TrainConfig(), select_best=select_best, env=replace(TrainConfig().env,
                  terminate_on="strict"))  # fmt: skip
    model = PPO("MlpPolicy", "Pendulum-v1", n_steps=8, batch_size=8, seed=0, device="cpu")
    session = TrainingSession(cfg, tmp_path, model, None, note=lambda m: None)
    monkeypatch.setattr(session, "_eval_rows", lambda: [])
    session.start(warm_started=False)
    weights = {}
    for step, *_ in STAGE2:
        model.policy.action_net.bias.data += 1.0  # a different policy at every evaluation
        weights[step] = policy_files(model, None)
        session.evaluate(step)
    assert session.schedule["best_step"] == kept_step
    for name, data in weights[kept_step].items():
        assert (tmp_path / "best" / name).read_bytes() == data, name
    history = [json.loads(line) for line in (tmp_path / "eval_history.jsonl").open()]
    assert [r["step"] for r in history if r.get("best")][-1] == kept_step
    assert _trial_summary(tmp_path)["best_eval"]["step"] == kept_step


# A tiny warm-started run: DAgger, then the critic alone up to step 200, evaluated every 64 steps
# (at 0, 64, 128 and 192 the actor is the imitated one; at 256 PPO has moved it).
FROZEN = """\
n_envs = 1
total_steps = 256
checkpoint_every = 256
eval_every = 64
eval_episodes = 2
[env]
episode_s = 4.0
[ppo]
n_steps = 64
batch_size = 64
n_epochs = 2
[imitation]
teacher = "pid"
iterations = 1
episodes_per_iteration = 1
epochs = 2
critic_warmup_steps = 200
"""


def test_an_evaluation_of_the_frozen_actor_repeats_the_last_one_exactly(tmp_path, monkeypatch):
    """While the critic trains alone, an evaluation repeats the last record instead of flying
    the same deterministic policy again: the history is the one every evaluation flown gives,
    byte for byte, and only the evaluations of a changed actor are flown."""
    from uwdock.dockcore.config import load_config
    from uwdock.rl.train.training import train

    (tmp_path / "train.toml").write_text(FROZEN)
    cfg = load_config(TrainConfig, tmp_path / "train.toml", section="train")
    flown = []
    real_rows = TrainingSession._eval_rows

    def counting(self):
        flown.append(int(self.model.num_timesteps))
        return real_rows(self)

    monkeypatch.setattr(TrainingSession, "_eval_rows", counting)
    train(cfg, tmp_path / "reused", progress=False)
    reused_flown = list(flown)
    monkeypatch.setattr(TrainingSession, "_frozen_summary", lambda self, step: None)
    flown.clear()
    train(cfg, tmp_path / "flown", progress=False)
    assert reused_flown == [0, 256] and flown == [0, 64, 128, 192, 256]
    a = (tmp_path / "reused" / "eval_history.jsonl").read_bytes()
    b = (tmp_path / "flown" / "eval_history.jsonl").read_bytes()
    assert a == b and len(a.splitlines()) == 5
    assert (tmp_path / "reused" / "eval_history.png").is_file()  # drawn when the run ended
    for name in ("model.json", "weights.npz"):
        assert (tmp_path / "reused" / name).read_bytes() == (tmp_path / "flown" / name).read_bytes()
