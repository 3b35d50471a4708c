"""Perturbations: each factor changes what the cameras see and nothing the expert does; drawn from the seed,
recorded in the episode, and offered by `generate --perturb` and `eval --perturb`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from demo_factory.cli import main
from demo_factory.generate import EpisodeRequest, run_episode
from demo_factory.generate.job import job_requests
from demo_factory.record import read_episode
from demo_factory.rollout import start_scene, start_views
from demo_factory.rollout.perturbations import (
    PERTURBATIONS,
    drawn_perturbations,
    parse_perturb_option,
    parse_perturbations,
)
from demo_factory.sim import DEFAULT_CAMERAS
from demo_factory.tasks import TASKS, get_task

SIZE = (48, 48)
# Each factor on two to three tasks, so that every task meets some factor (lookalike where it applies).
FACTOR_TASKS = {"lookalike": ["push_buttons", "tower", "reach_and_drag"]}
_OTHERS = [name for name in PERTURBATIONS if name != "lookalike"]
FACTOR_TASKS |= {name: [t for k, t in enumerate(t for t in TASKS if t not in FACTOR_TASKS["lookalike"])
                        if k % len(_OTHERS) == i] for i, name in enumerate(_OTHERS)}


def test_every_task_meets_some_factor():
    assert set(TASKS) <= {t for tasks in FACTOR_TASKS.values() for t in tasks}


@pytest.mark.parametrize("factor", list(PERTURBATIONS))
def test_each_factor_is_visible_and_leaves_the_expert_alone(factor):
    """The start renders differ from the unperturbed ones; the expert's keyframes are the same and it succeeds."""
    for name in FACTOR_TASKS[factor]:
        task = get_task(name)
        variation = task.split_variations("train")[0]
        plain = start_views(name, variation.id, 5, (), SIZE)
        perturbed = start_views(name, variation.id, 5, (factor,), SIZE)
        changed = max(int((np.abs(plain[c].astype(int) - perturbed[c]).sum(-1) > 12).sum()) for c in plain)
        assert changed >= 8, f"{factor} on {name}: {changed} pixels changed visibly"
        keyframes = []
        for names in ((), (factor,)):
            world = start_scene(task, variation, 5, DEFAULT_CAMERAS, SIZE, names)
            try:
                keyframes.append([k.pose for k in task.expert(world)])
            finally:
                world.close()
        assert keyframes[0] == keyframes[1], f"{factor} changed {name}'s expert keyframes"
        outcome = run_episode(EpisodeRequest(name, "train", variation.id, 5, SIZE, perturbations=(factor,)), None)
        assert outcome.kept, f"the expert failed {name} under {factor}: {outcome.reason}"


def test_draws_are_seeded_and_recorded(tmp_path):
    task = get_task("push_buttons")
    variation = task.split_variations("train")[0]
    drawn = []
    for _ in range(2):
        world = start_scene(task, variation, 11, DEFAULT_CAMERAS, SIZE, tuple(PERTURBATIONS))
        drawn.append(json.dumps(world.perturbations, sort_keys=True))
        world.close()
    assert drawn[0] == drawn[1]
    assert set(json.loads(drawn[0])) == set(PERTURBATIONS)
    other = start_scene(task, variation, 12, DEFAULT_CAMERAS, SIZE, ("lighting",))
    assert other.perturbations["lighting"] != json.loads(drawn[0])["lighting"]
    other.close()
    outcome = run_episode(EpisodeRequest("push_buttons", "train", variation.id, 11, SIZE,
                                         perturbations=("lighting", "distractors")), tmp_path)
    info = read_episode(outcome.path).info
    assert set(info.perturbations) == {"lighting", "distractors"}
    assert info.perturbations["lighting"] == json.loads(drawn[0])["lighting"]


def test_probabilities_draw_each_factor_independently():
    every = {name: 1.0 for name in PERTURBATIONS}
    assert drawn_perturbations(every, 3) == tuple(PERTURBATIONS)
    assert drawn_perturbations({name: 0.0 for name in PERTURBATIONS}, 3) == ()
    counts = sum(len(drawn_perturbations({"lighting": 0.3}, seed)) for seed in range(400))
    assert 90 < counts < 150
    # A factor's draw does not depend on which others are asked for.
    assert all(("lighting" in drawn_perturbations({"lighting": 0.5}, s))
               == ("lighting" in drawn_perturbations({"lighting": 0.5, "occluder": 0.5}, s)) for s in range(50))
    requests = job_requests("push_buttons", "train", 20, 0, perturb={"table_colour": 0.5}, image_size=SIZE)
    assert 0 < sum(bool(r.perturbations) for r in requests) < 20


def test_names_are_checked():
    assert parse_perturbations("lighting, occluder") == ("lighting", "occluder")
    assert "lookalike" not in parse_perturbations("all", get_task("slide_block_to_target"))
    assert "lookalike" not in parse_perturbations("all", get_task("open_drawer"))  # a drawer of a chest
    assert parse_perturb_option("lighting=0.25,occluder") == {"lighting": 0.25, "occluder": 0.5}
    with pytest.raises(ValueError, match="unknown perturbation 'fog'; accepted: lighting"):
        parse_perturbations("fog")
    with pytest.raises(ValueError, match="does not apply to slide_block_to_target: slide_block_to_target has no goal"):
        parse_perturbations("lookalike", get_task("slide_block_to_target"))
    with pytest.raises(ValueError, match="named twice"):
        parse_perturbations("lighting,lighting")
    with pytest.raises(ValueError, match="out of range; accepted: 0 to 1"):
        parse_perturb_option("lighting=1.5")


def test_generate_and_eval_take_perturb(tmp_path, capsys):
    out = tmp_path / "gen"
    assert main(["generate", "--task", "push_buttons", "--episodes", "2", "--image-size", "32", "--workers", "1",
                 "--perturb", "lighting=1,distractors=0", "--out", str(out)]) == 0
    for path in sorted(out.glob("*.mcap")):
        assert list(read_episode(path).info.perturbations) == ["lighting"]
    assert main(["inspect", str(sorted(out.glob("*.mcap"))[0])]) == 0
    assert "  perturbations: lighting\n" in capsys.readouterr().out
    summary = json.loads(next(out.glob("generation_summary_*.json")).read_text())
    assert "--perturb lighting=1,distractors=0" in summary["command"]
    dataset = tmp_path / "dataset"
    assert main(["convert", "--in", str(out), "--out", str(dataset)]) == 0
    card = (dataset / "README.md").read_text()
    assert "- perturbations (`generate --perturb`, docs/robustness.md): lighting in 2 of the 2 episodes; 0 unperturbed" in card
    rows = [e for path in sorted(dataset.glob("*/meta/demo_factory.json")) for e in json.loads(path.read_text())["episodes"]]
    assert [e["perturbations"] for e in rows] == [["lighting"], ["lighting"]]

    assert main(["generate", "--task", "open_drawer", "--episodes", "1", "--perturb", "lookalike",
                 "--out", str(tmp_path / "refused")]) == 2
    assert "--perturb: perturbation 'lookalike' does not apply to open_drawer: the first object" in capsys.readouterr().err
    assert not (tmp_path / "refused").exists()

    ev = tmp_path / "eval"
    assert main(["eval", "--expert", "--task", "push_buttons", "--splits", "train", "--episodes", "1",
                 "--image-size", "32", "--perturb", "occluder,lookalike", "--out", str(ev)]) == 0
    results = json.loads((ev / "results.json").read_text())
    assert {f: s["train"]["success_rate"] for f, s in results["perturbations"].items()} == {"occluder": 1.0,
                                                                                           "lookalike": 1.0}
    assert "| train | 100.0 | 100.0 | 100.0 | 100.0 |" in (ev / "results.md").read_text()
    assert (ev / "contact_occluder.png").stat().st_size > 0 and (ev / "contact_lookalike.png").is_file()
    rows = [json.loads(line) for line in (ev / "episodes.jsonl").read_text().splitlines()]
    assert [r["perturbations"] for r in rows] == [[], ["occluder"], ["lookalike"]]
    assert main(["eval", "--expert", "--task", "push_buttons", "--perturb", "fog", "--out", str(tmp_path / "e2")]) == 2
    assert "--perturb: unknown perturbation 'fog'" in capsys.readouterr().err


def test_lerobot_eval_env_takes_perturb():
    from demo_factory.evaluate.env import make_env
    from demo_factory.evaluate.lerobot_env import DemoFactoryEnv

    config = DemoFactoryEnv(task="push_buttons", perturb="lighting,occluder", image_height=32, image_width=32)
    env = make_env("push_buttons", **config.gym_kwargs)
    try:
        env.reset()
        assert env.episode.perturbations == ("lighting", "occluder")
        assert set(env.world.perturbations) == {"lighting", "occluder"}
    finally:
        env.close()
    with pytest.raises(ValueError, match="unknown perturbation 'fog'"):
        DemoFactoryEnv(task="push_buttons", perturb="fog")
