"""Language-conditioned reach in real MuJoCo, and its scripted expert (demonstrations, HG-DAgger takeovers)."""

from __future__ import annotations

import numpy as np

from edge_agent.robot import make_robot
from edge_agent.robots.lang_reach import COLOURS, LangReachArm
from edge_agent.teleop import TELEOPERATORS
from user.text import INSTRUCTION_KEY, decode_instruction


def run_episode(robot: LangReachArm, expert, policy=None) -> tuple[bool, int]:
    obs = robot.observe()
    expert.reset(obs)
    for _ in range(robot.max_episode_steps):
        action = expert.poll(obs)
        if action is None:
            action = policy(obs) if policy is not None else np.zeros(3, np.float32)
        robot.act(action)
        obs = robot.observe()
        if obs.terminated:
            return obs.success, expert.steps
    return False, expert.steps


def test_observation_names_one_of_three_rendered_targets() -> None:
    robot = make_robot("lang_reach_arm", "lang-0", seed=3)
    try:
        obs = robot.reset()
        spec = {f.name: tuple(f.shape) for f in robot.spec.observation}
        assert spec == {"state": (15,), INSTRUCTION_KEY: (64,), "camera.front": (64, 64, 3)}
        for name, shape in spec.items():
            assert obs.features[name].shape == shape
        text = decode_instruction(obs.features[INSTRUCTION_KEY])
        assert text == f"reach the {list(COLOURS)[robot.goal]} target" == obs.info["instruction"]
        image = obs.features["camera.front"].astype(int)
        red = (image[..., 0] > 150) & (image[..., 1] < 80) & (image[..., 2] < 80)
        blue = (image[..., 2] > 150) & (image[..., 0] < 80)
        assert red.any() and blue.any()  # the targets are in view
        goals = {make_robot("lang_reach_arm", "x", {"camera": False}, seed=s).goal for s in range(12)}
        assert goals == {0, 1, 2}
    finally:
        robot.close()


def test_expert_reaches_the_named_target() -> None:
    successes = 0
    for seed in range(5):
        robot = make_robot("lang_reach_arm", "lang-0", {"camera": False}, seed=seed)
        expert = TELEOPERATORS.build("lang_reach_expert", {"mode": "always"}, spec=robot.spec)
        ok, _ = run_episode(robot, expert)
        successes += ok
        assert not ok or np.linalg.norm(robot.ee_pos() - robot.targets[robot.goal]) < 0.03
    assert successes == 5


def test_expert_takes_over_only_when_the_policy_errs() -> None:
    robot = make_robot("lang_reach_arm", "lang-0", {"camera": False}, seed=1)
    idle = TELEOPERATORS.build("lang_reach_expert", {"mode": "intervene", "patience": 3}, spec=robot.spec)
    ok, expert_steps = run_episode(robot, idle)  # a policy that does nothing: the expert steps in and finishes
    assert ok and idle.takeovers >= 1 and expert_steps > 0

    robot.reset(seed=1)
    good = TELEOPERATORS.build("lang_reach_expert", {"mode": "intervene"}, spec=robot.spec)
    from edge_agent.teleoperators.lang_reach_expert import expert_action

    ok, expert_steps = run_episode(
        robot, good, policy=lambda o: expert_action(o.features["state"][:3], o.info["goal_pos"], robot.period)
    )
    assert ok and good.takeovers == 0 and expert_steps == 0


def test_touching_another_target_fails_the_episode() -> None:
    robot = make_robot("lang_reach_arm", "lang-0", {"camera": False}, seed=2)
    from edge_agent.teleoperators.lang_reach_expert import expert_action

    wrong = robot.targets[(robot.goal + 1) % 3]
    for _ in range(robot.max_episode_steps):
        robot.act(expert_action(robot.ee_pos(), wrong, robot.period))
        obs = robot.observe()
        if obs.terminated:
            break
    assert obs.terminated and not obs.success
