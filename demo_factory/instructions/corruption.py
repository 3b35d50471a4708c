"""Corrupted instructions: every palette colour word replaced by a synonym never used in training.

HiveFormer's "unseen corrupted" test renames the colours of an unseen variation (the paper's
examples: azure → light blue, maroon → dark red). Here the rule is strict: a synonym contains no
palette colour word at all, so that *no* word a policy saw as a colour in training survives in the
corrupted split ("light blue" would keep "blue"). The table is one-to-one, so a corrupted
instruction still names distinct colours distinctly.
"""

from __future__ import annotations

import re

from demo_factory.tasks.palette import COLOURS, SPELLINGS, canonical_colour

COLOUR_SYNONYMS: dict[str, str] = {
    "red": "scarlet",
    "maroon": "burgundy",
    "lime": "chartreuse",
    "green": "emerald",
    "blue": "cobalt",
    "navy": "midnight",
    "yellow": "lemon",
    "cyan": "aqua",
    "magenta": "fuchsia",
    "silver": "platinum",
    "gray": "ash",
    "orange": "tangerine",
    "olive": "khaki",
    "purple": "plum",
    "teal": "petrol",
    "azure": "cerulean",
    "violet": "indigo",
    "rose": "cerise",
    "black": "ebony",
    "white": "ivory",
}

# Every spelling of every palette colour, longest first so the alternation prefers whole names.
_COLOUR_WORD = re.compile(
    r"\b(" + "|".join(sorted([*COLOURS, *SPELLINGS], key=len, reverse=True)) + r")\b", re.IGNORECASE
)


def colour_words(text: str) -> list[str]:
    """The palette colour words (any spelling, any case) in ``text``, in order of appearance."""
    return [m.group(0) for m in _COLOUR_WORD.finditer(text)]


def corrupt_instruction(text: str) -> str:
    """``text`` with each palette colour word replaced by its unseen synonym (capitalisation kept)."""

    def replace(match: re.Match) -> str:
        word = match.group(0)
        synonym = COLOUR_SYNONYMS[canonical_colour(word)]
        if word.isupper() and len(word) > 1:
            return synonym.upper()
        return synonym.capitalize() if word[0].isupper() else synonym

    return _COLOUR_WORD.sub(replace, text)
