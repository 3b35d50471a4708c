"""Colour names -> CIELAB coordinates: what the instruction tokens of a colour name carry with `colour_features`.

A word-piece embedding says which word a token is, not which colour it names: "scarlet", never seen in training,
is as far from "red" as from "navy". People name colours in many ways, and a table of names gives each one its
colour. The table is matplotlib's: the 949 names of the xkcd colour survey (public domain), then the CSS4 names it
lacks, each "grey" name also spelt "gray". A phrase of up to three words is matched longest first ("dark blue"
before "blue"); hyphens and slashes read as spaces ("blue-green").
"""

import functools
import re

import numpy as np

MAX_WORDS = 3
# CIELAB's L in [0, 100], a and b in about [-128, 127]: scaled to about [-1, 1].
LAB_SCALE = np.array([100.0, 128.0, 128.0], dtype=np.float32)
WORD = re.compile(r"[a-z]+")
JOINER = re.compile(r"[\s\-/]+")


@functools.cache
def colour_table() -> dict[str, np.ndarray]:
    """Colour name (lower case, words separated by one space) -> its CIELAB coordinates, scaled (3,)."""
    import cv2
    from matplotlib import colors

    hex_codes = {name.lower(): code for name, code in colors.CSS4_COLORS.items()}
    hex_codes |= {name.removeprefix("xkcd:").replace("/", " "): code for name, code in colors.XKCD_COLORS.items()}
    hex_codes |= {name.replace("grey", "gray"): code for name, code in hex_codes.items() if "grey" in name}
    names = list(hex_codes)
    rgb = np.array([colors.to_rgb(hex_codes[name]) for name in names], dtype=np.float32)
    lab = cv2.cvtColor(rgb[:, None, :], cv2.COLOR_RGB2Lab)[:, 0, :] / LAB_SCALE
    return dict(zip(names, lab, strict=True))


def colour_spans(text: str) -> list[tuple[int, int, np.ndarray]]:
    """The colour names in ``text``: (start, end) character offsets and the colour's scaled CIELAB coordinates,
    in order, the longest name first where names overlap."""
    table = colour_table()
    words = list(WORD.finditer(text.lower()))
    spans, i = [], 0
    while i < len(words):
        for n in range(min(MAX_WORDS, len(words) - i), 0, -1):
            group = words[i:i + n]
            joined = all(JOINER.fullmatch(text[a.end():b.start()]) for a, b in zip(group, group[1:]))
            name = " ".join(w.group(0) for w in group)
            if joined and name in table:
                spans.append((group[0].start(), group[-1].end(), table[name]))
                i += n
                break
        else:
            i += 1
    return spans
