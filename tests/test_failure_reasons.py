"""Task-level failure reasons: a failed evaluation episode says where and how it went wrong, in the task's words.

Every rollout here is real (the simulator, the planner, the executor); the "policies" are scripted keyframes
that go wrong in one known way.
"""

import json

import numpy as np
import pybullet as p
import pytest

from demo_factory.evaluate.env import DenseEnv, KeyframeEnv, default_episodes
from demo_factory.evaluate.policies import CurrentPosePolicy
from demo_factory.evaluate.runner import evaluate_episode, summarise, write_results
from demo_factory.tasks.base import KeyframeTarget
from demo_factory.tasks.tower import KEYFRAMES_PER_CUBE


class Scripted:
    """Emits ``make(env)``'s keyframes, then holds still (the current pose) until the step limit."""

    name = "scripted"

    def __init__(self, make, before_step=None):
        self.make, self.before_step = make, before_step or {}

    def reset(self, env):
        self.keyframes = [np.r_[k.pose, k.gripper_open] for k in self.make(env)]

    def act(self, env):
        if env.steps in self.before_step:
            self.before_step[env.steps](env)
        if env.steps < len(self.keyframes):
            return self.keyframes[env.steps]
        robot = env.frame.robot
        return np.r_[robot.gripper_pose, robot.gripper_open]


def raised(target: KeyframeTarget, dz: float, gripper_open: float | None = None) -> KeyframeTarget:
    pose = list(target.pose)
    pose[2] += dz
    return KeyframeTarget(tuple(pose), target.gripper_open if gripper_open is None else gripper_open, target.motion)


def run(task: str, policy, split: str = "train", index: int = 0) -> dict:
    episode = default_episodes(task, split, index + 1)[index]
    env = KeyframeEnv(task, [episode], image_size=(32, 32))
    try:
        return evaluate_episode(env, policy, episode)
    finally:
        env.close()


# -- push_buttons -----------------------------------------------------------------------------------
def test_pressing_the_wrong_button_first_is_wrong_button_pressed_at_subgoal_1():
    record = run("push_buttons", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)), "test")
    first = default_episodes("push_buttons", "test", 1)[0]
    assert not record["success"]
    assert (record["failure_reason"], record["failure_subgoal"]) == ("wrong button pressed", 1)
    assert record["failure_detail"].startswith("pressed ")
    assert record["failure_detail"].endswith(f" where {_instructed('push_buttons', first)[0]} was next")


def test_a_press_that_stops_short_of_3_mm_is_press_too_shallow():
    """The expert pushes the cap 9 mm; landing 8.5 mm high moves it ~2 mm, which is no press."""
    def shallow(env):
        approach, press, retreat = env.expert_keyframes[:3]
        return [approach, raised(press, 0.0085), retreat]

    record = run("push_buttons", Scripted(shallow), "test")
    assert (record["failure_reason"], record["failure_subgoal"]) == ("press too shallow", 1)
    travel = float(record["failure_detail"].split(" cap moved ")[1].split(" mm")[0])
    assert 1.0 <= travel < 3.0, record["failure_detail"]


def test_pressing_nothing_is_the_step_limit():
    record = run("push_buttons", CurrentPosePolicy())
    assert record["failure_reason"] == "step limit" and record["failure_subgoal"] is None
    assert record["steps"] == record["step_limit"]


# -- tower ------------------------------------------------------------------------------------------
GRASP = KEYFRAMES_PER_CUBE // 2  # the expert's keyframes that grasp and lift a cube


def test_closing_the_gripper_above_the_cube_is_grasp_missed():
    def too_high(env):
        over, close, lift = env.expert_keyframes[:GRASP]  # down to the cube and close at the end of the move
        return [over, raised(close, 0.04), lift]

    record = run("tower", Scripted(too_high))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("grasp missed", 1), record["failure_detail"]


def test_closing_the_gripper_in_the_air_near_no_cube_is_grasp_missed_not_the_step_limit():
    def in_the_air(env):
        over = env.expert_keyframes[0]  # 10 cm above the first cube
        return [over, raised(over, 0.0, gripper_open=0.0)]

    record = run("tower", Scripted(in_the_air))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("grasp missed", 1), record["failure_detail"]
    assert record["failure_detail"].startswith("the gripper closed near no cube, ")
    assert 6 <= int(record["failure_detail"].split(", ")[1].split(" cm")[0]) <= 20, record["failure_detail"]


def test_letting_go_of_a_lifted_cube_high_above_the_table_is_cube_dropped():
    def drop(env):
        grasp = env.expert_keyframes[:GRASP]
        return grasp + [KeyframeTarget(grasp[-1].pose, 1.0, "gripper")]

    record = run("tower", Scripted(drop))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("cube dropped", 1), record["failure_detail"]


def test_letting_go_of_a_cube_3_cm_beside_the_target_is_cube_placed_off_target():
    def beside(env):
        keyframes = env.expert_keyframes[:KEYFRAMES_PER_CUBE]
        return keyframes[:GRASP] + [KeyframeTarget((k.pose[0] + 0.03, *k.pose[1:]), k.gripper_open, k.motion)
                                    for k in keyframes[GRASP:]]

    record = run("tower", Scripted(beside))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("cube placed off target", 1), record["failure_detail"]
    assert "was let go 3.0 cm from the target spot" in record["failure_detail"]


def test_a_distractor_on_the_target_is_wrong_cube_placed():
    record = run("tower", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)[:KEYFRAMES_PER_CUBE]))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("wrong cube placed", 1), record["failure_detail"]
    assert "(not in the instruction) stands on the target where" in record["failure_detail"]


def test_a_lifted_cube_never_let_go_is_cube_still_held():
    """The expert's grasp and lift, then the policy holds still until the step limit."""
    record = run("tower", Scripted(lambda env: env.expert_keyframes[:GRASP]))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("cube still held", 1), record["failure_detail"]
    assert "never let go" in record["failure_detail"]


def test_lifting_a_distractor_instead_of_the_first_cube_is_wrong_cube_picked():
    record = run("tower", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)[:GRASP]))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("wrong cube picked", 1), record["failure_detail"]
    assert "(not in the instruction) cube where" in record["failure_detail"]


def test_a_placed_cube_that_leaves_the_target_is_tower_knocked_over():
    """The first cube is placed as the expert does, then knocked off the target (moved by hand)."""
    def knock(env):
        task = env.sim_task
        cube = task.cubes[task.instructed.words[0]]
        assert task.in_place(env.world, task.instructed.words[0], 0)
        p.resetBasePositionAndOrientation(cube, (*(task.target + [0.08, 0.0]), 0.0225), (0, 0, 0, 1),
                                          physicsClientId=env.world.client)

    record = run("tower", Scripted(lambda env: env.expert_keyframes[:KEYFRAMES_PER_CUBE],
                                   before_step={KEYFRAMES_PER_CUBE: knock}))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("tower knocked over", 1), record["failure_detail"]


def test_a_policy_that_does_nothing_in_a_dense_env_reaches_the_step_limit():
    episode = default_episodes("tower", "train", 1)[0]
    env = DenseEnv("tower", [episode], image_size=(32, 32), max_seconds=0.5)
    try:
        record = evaluate_episode(env, CurrentPosePolicy(), episode)
    finally:
        env.close()
    assert record["failure_reason"] == "step limit" and record["steps"] == 10


# -- the summary ------------------------------------------------------------------------------------
def test_the_reasons_add_up_to_the_failures_overall_per_variation_and_in_results_md(tmp_path):
    episodes = default_episodes("tower", "train", 3)
    env = KeyframeEnv("tower", episodes, image_size=(32, 32))
    policies = [
        Scripted(lambda env: env.expert_keyframes),  # succeeds
        Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)[:KEYFRAMES_PER_CUBE]),
        CurrentPosePolicy(),
    ]
    try:
        records = [evaluate_episode(env, policy, e) for e in episodes for policy in policies]
    finally:
        env.close()
    summary = summarise(records)
    failures = sum(not r["success"] for r in records)
    assert failures == 6 and summary["failure_reasons"] == {"wrong cube placed": 3, "step limit": 3}
    assert summary["failure_subgoals"] == {"wrong cube placed": {"1": 3}}
    for block in summary["per_variation"].values():
        assert sum(block["failure_reasons"].values()) == round(block["episodes"] * (1 - block["success_rate"]))
    write_results(tmp_path, "scripted", "tower", {"train": summary, "test": summarise(records[:1])})
    table = (tmp_path / "results.md").read_text()
    assert "| failure reason | train | test |" in table
    assert "| wrong cube placed | 3 | 0 |" in table and "| step limit | 3 | 0 |" in table
    assert "| **failed episodes** | 6 | 0 |" in table
    assert json.loads((tmp_path / "results.json").read_text())["splits"]["train"]["failure_reasons"]["step limit"] == 3


def _instructed(task: str, episode) -> tuple[str, ...]:
    from demo_factory.tasks import get_task

    return get_task(task).variation(episode.variation_id).words


@pytest.mark.parametrize("task", ["push_buttons", "tower"])
def test_the_expert_has_no_failure(task):
    record = run(task, Scripted(lambda env: env.expert_keyframes))
    assert record["success"] and record["failure_reason"] is None and record["failure_subgoal"] is None


# -- tasks with one goal among a few ----------------------------------------------------------------
@pytest.mark.parametrize("task, wrong, reason", [
    ("turn_tap", lambda env: env.sim_task.wrong_keyframes(env.world), "wrong tap turned"),
    ("stack_wine", lambda env: env.sim_task.expert_with(
        env.world, slot=next(s for s in env.sim_task.palette if s != env.sim_task.slot)), "wrong slot"),
    ("put_money_in_safe", lambda env: env.sim_task.wrong_keyframes(env.world), "wrong shelf"),
])
def test_the_other_goal_of_a_few_is_named(task, wrong, reason):
    record = run(task, Scripted(wrong))
    assert (record["failure_reason"], record["failure_subgoal"]) == (reason, 1), record
    assert "instructed" in record["failure_detail"]


# -- pick_and_lift: where the lift went wrong ---------------------------------------------------------
def test_pick_and_lift_names_a_lift_off_target_a_wrong_block_and_a_missed_grasp():
    def short_of_target(env):  # the expert's grasp, then the lift stopping 10 cm below the sphere
        keyframes = env.expert_keyframes
        return [*keyframes[:-1], raised(keyframes[-1], -0.10)]

    record = run("pick_and_lift", Scripted(short_of_target))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("block off target", 1), record
    assert "cm from the target sphere" in record["failure_detail"]
    record = run("pick_and_lift", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)))
    assert record["failure_reason"] == "wrong block picked" and "instructed" in record["failure_detail"]
    assert run("pick_and_lift", CurrentPosePolicy())["failure_reason"] == "block not held"
    assert run("pick_and_lift", Scripted(lambda env: env.expert_keyframes))["failure_reason"] is None


# -- stack_blocks and reach_and_drag --------------------------------------------------------------------
def test_stack_blocks_names_the_level_it_stopped_at():
    from demo_factory.tasks.stack_blocks import N_STACK

    per_block = 8  # grasp (4) + place (4)
    record = run("stack_blocks", Scripted(lambda env: env.expert_keyframes[:per_block]))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("stack incomplete", 2), record["failure_detail"]
    assert record["failure_detail"].startswith(f"1 of {N_STACK} ")
    record = run("stack_blocks", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)))
    assert (record["failure_reason"], record["failure_subgoal"]) == ("wrong block stacked", 3), record["failure_detail"]
    record = run("stack_blocks", Scripted(lambda env: env.expert_keyframes[:per_block + 3]))  # grasped, not placed
    assert (record["failure_reason"], record["failure_subgoal"]) == ("block still held", 2), record["failure_detail"]


def test_reach_and_drag_says_where_the_cube_ended():
    record = run("reach_and_drag", Scripted(lambda env: env.sim_task.wrong_keyframes(env.world)))
    assert record["failure_reason"] == "cube on wrong target", record["failure_detail"]
    record = run("reach_and_drag", Scripted(lambda env: env.expert_keyframes[:3]))  # the stick grasped, no drag
    assert record["failure_reason"] == "cube not moved", record["failure_detail"]
    record = run("reach_and_drag", CurrentPosePolicy())
    assert record["failure_reason"] == "stick not held", record["failure_detail"]
