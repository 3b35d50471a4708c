"""A grammar of synthetic instructions: tens of ways to say one variation's instruction, for training.

A policy trained on a few sentence shapes per variation learns those shapes, not the language: a phrasing unlike
them scores about chance. The grammar varies what people vary (the HiveFormer authors' human sentences are the
model): the verb, how the order is said, the object noun or none, colour names other than the palette's own,
politeness and filler, capitals and full stops, and now and then a typo. A task gives its sentence frames
(``Frames``); ``phrasings`` draws distinct sentences from them, the same list for the same variation every time
(seeded by the task and the variation), and training draws one of them per sample.

Kept apart by construction, and tested (tests/test_instructions.py):

- from the corrupted split: no colour name here is a synonym of the corrupted split (``COLOUR_SYNONYMS``);
- from the held-out phrasings (``Task.held_out_phrasings``): none of their marker words (``HELD_OUT_MARKERS``)
  appears in a sentence of the grammar.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Callable, Sequence

import numpy as np

# Other names people give the palette's colours (the authors' human sentences say "dark blue", "light blue",
# "brown", "grey"...), none of them a corrupted-split synonym.
COLOUR_NAMES: dict[str, tuple[str, ...]] = {
    "red": ("crimson",),
    "maroon": ("dark red", "brown"),
    "lime": ("light green", "bright green"),
    "green": ("dark green",),
    "navy": ("dark blue",),
    "azure": ("sky blue", "light blue"),
    "cyan": ("turquoise",),
    "teal": ("dark cyan", "blue-green"),
    "olive": ("dark yellow",),
    "orange": ("amber",),
    "silver": ("light grey", "light gray"),
    "gray": ("grey",),
    "rose": ("pink",),  # the name most of the authors' human sentences give it
}
# Words and phrases of the held-out phrasings that no grammar sentence uses.
HELD_OUT_MARKERS = ("activate", "depress", "followed by", "afterwards", "lastly", "comes first", "wrap up",
                    "in sequence", "once", "lay", "rest", "crown", "ground up", "sits", "middle", "nothing more")

PREFIXES = ("please ", "now ", "could you ", "can you ", "go ahead and ", "I want you to ", "you should ",
            "robot, ", "ok, ")
SUFFIXES = (" please", ", thanks", " now", ", thank you")
SYNONYM_SHARE = 0.3  # how often a colour with other names gets one of them
POLITE_SHARE = 0.45
TYPO_SHARE = 0.1
CAPITALISED_SHARE = 0.5


# A task's sentence frames for one variation: each takes a colour renderer (palette colour → the name this sentence
# uses) and an rng, and returns a sentence.
Frames = Sequence[Callable[[Callable[[str], str], np.random.Generator], str]]


def pick(rng: np.random.Generator, options: Sequence[str]) -> str:
    return options[int(rng.integers(len(options)))]


def listed(names: Sequence[str]) -> str:
    """"a", "a and b", "a, b and c"."""
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def typo(sentence: str, rng: np.random.Generator, keep: Sequence[str]) -> str:
    """One slip of the keyboard in a word of four letters or more that is no colour name (``keep``): two letters
    swapped, one dropped or one doubled."""
    kept = {w for name in keep for w in re.findall(r"[a-z]+", name)}
    words = [m for m in re.finditer(r"[a-z]{4,}", sentence) if m.group(0) not in kept]
    if not words:
        return sentence
    word = words[int(rng.integers(len(words)))]
    text, i = word.group(0), 1 + int(rng.integers(len(word.group(0)) - 2))
    slip = int(rng.integers(3))
    changed = (text[:i] + text[i + 1] + text[i] + text[i + 2:] if slip == 0 else
               text[:i] + text[i + 1:] if slip == 1 else text[:i] + text[i] + text[i:])
    return sentence[:word.start()] + changed + sentence[word.end():]


def phrasings(task: str, words: Sequence[str], frames: Frames, count: int, first: Sequence[str] = ()) -> list[str]:
    """``first`` (the task's templates), then distinct sentences drawn from ``frames`` until there are ``count``
    (or the frames give no new one in many tries): the same list for the same task and variation every time."""
    rng = np.random.default_rng(zlib.crc32(f"{task}:{'/'.join(words)}".encode()))
    sentences = list(dict.fromkeys(first))
    seen = set(sentences)
    for _ in range(50 * count):
        if len(sentences) >= count:
            break
        names = {c: pick(rng, COLOUR_NAMES[c]) if c in COLOUR_NAMES and rng.random() < SYNONYM_SHARE else c
                 for c in words}
        sentence = frames[int(rng.integers(len(frames)))](names.__getitem__, rng)
        if rng.random() < POLITE_SHARE:
            sentence = pick(rng, PREFIXES) + sentence if rng.random() < 0.7 else sentence + pick(rng, SUFFIXES)
        if rng.random() < TYPO_SHARE:
            sentence = typo(sentence, rng, list(names.values()))
        if rng.random() < CAPITALISED_SHARE:
            sentence = sentence[0].upper() + sentence[1:] + "."
        if sentence not in seen:
            seen.add(sentence)
            sentences.append(sentence)
    return sentences
