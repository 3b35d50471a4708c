"""Which instruction encoder says the order, and the colour? A linear probe on the colour words' token features.

    python -m demo_factory.tools.order_probe [--task push_buttons] [--target order|colour] [--encoder minilm_causal ...]

A policy follows "press red, then blue" only if the features of each colour word tell which press it names, and
follows "press scarlet" only if they tell the colour. This fits a multinomial logistic regression from a colour
word's token features to its press (1st, 2nd, 3rd; ``--target order``) or to its palette colour (``--target colour``)
on the training sentences of the task's train variations (its templates and grammar, `Task.paraphrases`) and scores
it on sentences it never saw: the held-out phrasings, the test variations' templates with their colours renamed (the
corrupted split's sentences) and the paper authors' human-written sentences of the test variations (those whose
every colour is named by a palette or grammar colour name). Each encoder is the plugin's, as a policy gets it;
``position`` is the token's index alone. About two minutes on a CPU, no training run.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence

import torch

from demo_factory.instructions import (COLOUR_SYNONYMS, corrupt_instruction, load_human_instructions,
                                       shipped_human_instructions)
from demo_factory.tasks.grammar import COLOUR_NAMES
from demo_factory.tasks.palette import COLOURS, canonical_colour
from demo_factory.tasks.registry import TASKS

ENCODERS = ("minilm", "minilm_causal", "minilm_words", "position")
TARGETS = {"order": "press", "colour": "colour"}
PAPER_TASKS = tuple(name for name, task in TASKS.items() if task.paper_numbering is not None)


def colour_mentions(sentence: str, words: Sequence[str]) -> list[tuple[int, int, int]] | None:
    """(start, end, press) of every mention of the sequence's colours, by their palette or grammar names; None
    when a colour is not mentioned or two mentions overlap (the sentence says it another way)."""
    low, found = sentence.lower(), []
    for press, colour in enumerate(words):
        names = sorted({colour, *COLOUR_NAMES.get(colour, ()), *(("grey",) if colour == "gray" else ())},
                       key=len, reverse=True)
        mentions = []
        for name in names:
            mentions += [(m.start(), m.end(), press) for m in re.finditer(rf"\b{re.escape(name)}\b", low)
                         if not any(a <= m.start() < b for a, b, _ in mentions)]
        if not mentions:
            return None
        found += mentions
    found.sort()
    return None if any(b[0] < a[1] for a, b in zip(found, found[1:])) else found


def colour_tokens(tokenizer, sentences: list[tuple[str, list]]) -> list[tuple[int, int, int]]:
    """(sentence, token, press) of each colour mention's first word-piece token."""
    rows = []
    for i, (sentence, mentions) in enumerate(sentences):
        offsets = tokenizer(sentence, return_offsets_mapping=True)["offset_mapping"]
        for start, end, press in mentions:
            rows.append((i, next(k for k, (a, b) in enumerate(offsets) if b > a and start <= a and b <= end), press))
    return rows


def features(encoder_name: str, sets: dict[str, list[tuple[str, list]]], rows: dict[str, list],
             width: int = 64) -> dict[str, torch.Tensor]:
    """Each set's colour-word features: the encoder's token features, or the one-hot token index (``position``)."""
    if encoder_name == "position":
        return {name: torch.nn.functional.one_hot(torch.tensor([min(k, width - 1) for _, k, _ in r]), width).float()
                for name, r in rows.items()}
    from lerobot_policy_hiveformer.text_encoders import PretrainedTransformerInstructionEncoder, minilm_model_dir

    encoder = PretrainedTransformerInstructionEncoder(minilm_model_dir(), words_only=encoder_name == "minilm_words",
                                                      causal=encoder_name == "minilm_causal")
    encoded = {name: encoder._encode_new([s for s, _ in items]) for name, items in sets.items()}
    return {name: torch.stack([encoded[name][i][k] for i, k, _ in r]) for name, r in rows.items()}


def fit_probe(x: torch.Tensor, y: torch.Tensor, classes: int, weight_decay: float = 1e-3) -> torch.nn.Linear:
    """Multinomial logistic regression on standardised features (L-BFGS, L2)."""
    torch.manual_seed(0)
    probe = torch.nn.Linear(x.shape[1], classes)
    optimiser = torch.optim.LBFGS(probe.parameters(), max_iter=500, line_search_fn="strong_wolfe")

    def loss():
        optimiser.zero_grad()
        value = torch.nn.functional.cross_entropy(probe(x), y) + weight_decay * probe.weight.square().sum()
        value.backward()
        return value

    optimiser.step(loss)
    return probe


def sentence_sets(task_name: str, target: str = "order") -> dict[str, list[tuple[str, list]]]:
    """Each set's sentences with their colour mentions, labelled by the press (``order``) or by the palette colour
    (``colour``). The corrupted set is the test variations' templates with their colours renamed, as the
    ``test_unseen_corrupted`` split's. The order target trains on the variations of more than one colour."""
    task = TASKS[task_name]()
    train = [v for v in task.splits["train"] if target == "colour" or len(v.words) > 1]
    test = {v.id: v for v in task.splits["test"] if target == "colour" or len(v.words) > 1}
    human = [(row.instruction, row.words) for row in load_human_instructions(shipped_human_instructions(task_name))
             if row.task == task_name and row.variation_id in test]
    synonyms = {name: COLOUR_SYNONYMS[canonical_colour(name)] for v in test.values() for name in v.words}
    sets = {"train": [(s, v.words, v.words) for v in train for s in task.paraphrases(v)],
            "held-out phrasings": [(s, v.words, v.words) for v in test.values() for s in task.held_out_phrasings(v)],
            "corrupted": [(corrupt_instruction(s), [synonyms[w] for w in v.words], v.words)
                          for v in test.values() for s in task.synthetic_instructions(v)],
            "human": [(s, words, words) for s, words in human]}
    colour_ids = {name: i for i, name in enumerate(COLOURS)}

    def label(press: int, words: Sequence[str]) -> int:
        return press if target == "order" else colour_ids[canonical_colour(words[press])]

    return {name: [(s, [(a, b, label(p, words)) for a, b, p in m]) for s, names, words in items
                   if (m := colour_mentions(s, names))] for name, items in sets.items()}


def probe_table(task_name: str, encoders: Sequence[str], target: str = "order") -> list[dict]:
    """Per encoder, the probe's accuracy on each sentence set, and the share of the commonest label (the baseline)."""
    from lerobot_policy_hiveformer.text_encoders import minilm_model_dir
    from transformers import AutoTokenizer

    tokenizer = AutoTokenizer.from_pretrained(minilm_model_dir(), local_files_only=True)
    sets = sentence_sets(task_name, target)
    rows = {name: colour_tokens(tokenizer, items) for name, items in sets.items()}
    labels = {name: torch.tensor([p for *_, p in r]) for name, r in rows.items()}
    classes = int(labels["train"].max()) + 1
    commonest = torch.mode(labels["train"]).values
    table = [{"encoder": f"commonest {TARGETS[target]}",
              **{name: float((y == commonest).float().mean()) for name, y in labels.items()}}]
    for name in encoders:
        x = features(name, sets, rows)
        mean, std = x["train"].mean(0), x["train"].std(0) + 1e-6
        probe = fit_probe((x["train"] - mean) / std, labels["train"], classes)
        with torch.no_grad():
            table.append({"encoder": name, **{s: float((probe((x[s] - mean) / std).argmax(1) == labels[s]).float()
                                                       .mean()) for s in sets}})
    return [{**row, "colour words": {s: len(r) for s, r in rows.items()}} for row in table]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demo_factory.tools.order_probe",
                                     description=__doc__.split("\n\n")[2],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="push_buttons", choices=PAPER_TASKS,
                        help="a task with the paper's variations and human sentences (default: push_buttons)")
    parser.add_argument("--target", default="order", choices=TARGETS,
                        help="what the probe reads from a colour word: its step in the sequence (order) or its palette "
                             "colour (colour: can a renamed colour of the corrupted split be told?) (default: order)")
    parser.add_argument("--encoder", action="append", choices=ENCODERS,
                        help=f"repeatable (default: all: {', '.join(ENCODERS)})")
    args = parser.parse_args(argv)
    table = probe_table(args.task, args.encoder or ENCODERS, args.target)
    counts = table[0]["colour words"]
    question = "which step of the sequence (press, cube)" if args.target == "order" else "which palette colour"
    print(f"{args.task}: {question} a colour word names, from its features "
          "(colour words: " + ", ".join(f"{name} {n}" for name, n in counts.items()) + ")")
    print("| encoder | " + " | ".join(counts) + " |\n|---|" + "---|" * len(counts))
    for row in table:
        print(f"| {row['encoder']} | " + " | ".join(f"{100 * row[name]:.1f}" for name in counts) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
