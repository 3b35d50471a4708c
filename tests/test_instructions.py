"""Instruction tools: colour-word corruption, the human-instruction file format and assignment."""

import json

import pytest

from demo_factory.instructions import (
    COLOUR_SYNONYMS,
    HumanInstructionError,
    assign_human_instructions,
    colour_words,
    corrupt_instruction,
    load_human_instructions,
    shipped_human_instructions,
)
from demo_factory.instructions.human import variations_in_file
from demo_factory.tasks import get_task
from demo_factory.tasks.palette import COLOURS


def test_corruption_replaces_every_colour_word_of_every_synthetic_instruction():
    for name in ("push_buttons", "tower"):
        task = get_task(name)
        for variation in task.split_variations("test"):
            for text in task.synthetic_instructions(variation):
                corrupted = corrupt_instruction(text)
                assert colour_words(corrupted) == [], corrupted
                for colour in variation.words:
                    assert COLOUR_SYNONYMS[colour] in corrupted


def test_corruption_table_is_one_to_one_and_free_of_palette_words():
    assert set(COLOUR_SYNONYMS) == set(COLOURS)
    assert len(set(COLOUR_SYNONYMS.values())) == len(COLOURS)
    assert all(colour_words(s) == [] for s in COLOUR_SYNONYMS.values())


def test_corruption_handles_spellings_case_and_word_boundaries():
    assert corrupt_instruction("Push the Navy button, then the GREY one") == "Push the Midnight button, then the ASH one"
    assert corrupt_instruction("the greenish redstone") == "the greenish redstone"  # not whole colour words
    assert corrupt_instruction("push the navy button") == corrupt_instruction("push the navy button")


@pytest.mark.parametrize("task, count", [("push_buttons", 62), ("tower", 100)])
def test_shipped_human_instructions_are_the_papers_and_name_test_variations(task, count):
    rows = [r for r in load_human_instructions(shipped_human_instructions(task)) if r.task == task]
    assert len(rows) == count
    test_ids = {v.id for v in get_task(task).split_variations("test")}
    assert {r.variation_id for r in rows} <= test_ids
    assert all(r.language == "en" and r.record_id for r in rows)
    texts = [r.instruction.lower() for r in rows]
    assert any("grey" in t for t in texts) and any("gray" in t for t in texts)


def _write(tmp_path, rows):
    path = tmp_path / "human.jsonl"
    path.write_text("\n".join(r if isinstance(r, str) else json.dumps(r) for r in rows) + "\n")
    return path


def _first_test(task_name):
    return get_task(task_name).split_variations("test")[0]


GOOD = {"task": "push_buttons", "colours": list(_first_test("push_buttons").words), "instruction": "tap it"}


@pytest.mark.parametrize("bad, message", [
    ("{not json", "not valid JSON"),
    ({**GOOD, "task": "juggle"}, "unknown task 'juggle'; accepted: push_buttons, tower"),
    ({**GOOD, "colours": ["mauve"]}, "unknown colour 'mauve'"),
    ({**GOOD, "colours": list(get_task("push_buttons").split_variations("train")[0].words)}, "is a train variation of push_buttons"),
    ({**GOOD, "colours": None, "variation_id": get_task("push_buttons").split_variations("train")[0].id}, "would leak train data into a test split"),
    ({"task": "push_buttons", "instruction": "tap it"}, "no variation"),
    ({**GOOD, "instruction": "  "}, "instruction is missing or empty"),
    ({**GOOD, "instruction": "Tap  IT"}, "duplicate instruction 'Tap  IT' (same as line 1)"),
    ({**GOOD, "speaker": "x"}, "unknown field 'speaker'"),
    ({**GOOD, "variation_id": get_task("push_buttons").split_variations("test")[1].id}, "but colours say"),
])
def test_bad_human_instruction_rows_name_the_line(tmp_path, bad, message):
    if isinstance(bad, dict) and bad.get("colours") is None:
        bad = {k: v for k, v in bad.items() if k != "colours"}
    path = _write(tmp_path, [GOOD, "", bad])
    with pytest.raises(HumanInstructionError) as error:
        load_human_instructions(path)
    assert f"{path}:3: " in str(error.value) and message in str(error.value)


def test_rows_accept_ids_colour_strings_and_grey_spelling(tmp_path):
    variation = next(v for v in get_task("tower").split_variations("test") if "gray" in v.words)
    path = _write(tmp_path, [
        {"task": "tower", "colours": ", ".join(variation.words).replace("gray", "Grey"), "instruction": "a"},
        {"task": "tower", "variation_id": variation.id, "instruction": "b", "author": "me", "language": "fr"},
    ])
    rows = load_human_instructions(path)
    assert [r.variation_id for r in rows] == [variation.id, variation.id]
    assert [r.line for r in rows] == [1, 2] and rows[1].language == "fr" and rows[0].language == "en"
    assert variations_in_file(path, get_task("tower")) == [variation]


def test_assignment_uses_every_row_and_every_episode(tmp_path):
    a, b, c = get_task("push_buttons").split_variations("test")[:3]
    path = _write(tmp_path, [
        {"task": "push_buttons", "variation_id": a.id, "instruction": f"a{i}"} for i in range(3)
    ] + [{"task": "push_buttons", "variation_id": b.id, "instruction": "b0"},
         {"task": "push_buttons", "variation_id": c.id, "instruction": "c0"}])
    rows = load_human_instructions(path)
    episodes = {a.id: ["a-ep0"], b.id: ["b-ep0", "b-ep1"], 999: ["other"]}
    result = assign_human_instructions(episodes, rows)
    pairs = [(e, r.instruction) for e, r in result.pairs]
    assert pairs == [("a-ep0", "a0"), ("a-ep0", "a1"), ("a-ep0", "a2"), ("b-ep0", "b0"), ("b-ep1", "b0")]
    assert [r.instruction for r in result.rows_without_episodes] == ["c0"]
    assert result.episodes_without_rows == ["other"]


@pytest.mark.parametrize("task_name", ["push_buttons", "tower"])
def test_the_grammar_gives_tens_of_distinct_sentences_a_variation_the_same_each_time(task_name):
    task = get_task(task_name)
    variations = task.split_variations("train") + task.split_variations("test")
    distinct = [len(set(task.paraphrases(v))) for v in variations]
    assert sum(distinct) / len(distinct) >= 30
    for v in variations[::17]:
        phrasings = task.paraphrases(v)
        assert phrasings[:len(task.synthetic_instructions(v))] == task.synthetic_instructions(v)  # templates first
        assert phrasings == task.paraphrases(v)  # deterministic
        assert len(phrasings) == len(set(phrasings))


@pytest.mark.parametrize("task_name", ["push_buttons", "tower"])
def test_grammar_sentences_name_the_colours_in_order_and_stay_apart_from_the_test_splits(task_name):
    """Every sentence names the variation's colours in order (by the palette name or another name of it, never
    mangled by a typo); none uses a corrupted-split synonym or a word of the held-out phrasings; no held-out
    phrasing is a paraphrase of any variation."""
    import re

    from demo_factory.tasks.grammar import COLOUR_NAMES, HELD_OUT_MARKERS

    task = get_task(task_name)
    banned = [*COLOUR_SYNONYMS.values(), *HELD_OUT_MARKERS]
    training = set()
    for v in task.split_variations("train") + task.split_variations("test"):
        for sentence in task.paraphrases(v):
            training.add(sentence)
            found = [m for m in banned if re.search(rf"\b{re.escape(m)}\b", sentence, re.IGNORECASE)]
            assert not found, (sentence, found)
            names = {n: c for c in v.words for n in (c, *COLOUR_NAMES.get(c, ()))}
            pattern = "|".join(re.escape(n) for n in sorted(names, key=len, reverse=True))
            text = sentence.lower()
            if task_name == "tower":  # its target is "the grey square" or "the grey target"
                text = re.sub(r"\b(on|onto|to) the grey \w+", "on the target", text)
            named = [names[n] for n in re.findall(rf"\b({pattern})\b", text)]
            assert list(dict.fromkeys(named)) == list(v.words), (sentence, v.words)
    for v in task.split_variations("test"):
        held_out = task.held_out_phrasings(v)
        assert held_out and not set(held_out) & training
        assert all(any(re.search(rf"\b{re.escape(m)}\b", t, re.IGNORECASE) for m in HELD_OUT_MARKERS) for t in held_out)
        assert task.held_out_instruction(v, 5) in held_out
