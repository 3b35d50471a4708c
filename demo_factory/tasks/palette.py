"""The RLBench colour palette used by the multi-variation tasks (names and RGB in [0, 1])."""

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.0, 0.0),
    "maroon": (0.5, 0.0, 0.0),
    "lime": (0.0, 1.0, 0.0),
    "green": (0.0, 0.5, 0.0),
    "blue": (0.0, 0.0, 1.0),
    "navy": (0.0, 0.0, 0.5),
    "yellow": (1.0, 1.0, 0.0),
    "cyan": (0.0, 1.0, 1.0),
    "magenta": (1.0, 0.0, 1.0),
    "silver": (0.75, 0.75, 0.75),
    "gray": (0.5, 0.5, 0.5),
    "orange": (1.0, 0.5, 0.0),
    "olive": (0.5, 0.5, 0.0),
    "purple": (0.5, 0.0, 0.5),
    "teal": (0.0, 0.5, 0.5),
    "azure": (0.0, 0.5, 1.0),
    "violet": (0.5, 0.0, 1.0),
    "rose": (1.0, 0.0, 0.5),
    "black": (0.0, 0.0, 0.0),
    "white": (1.0, 1.0, 1.0),
}

# RLBench's push-buttons palette leaves out red and lime (a pressed button lights up green-ish).
PUSH_BUTTON_COLOURS: tuple[str, ...] = tuple(c for c in COLOURS if c not in ("red", "lime"))
TOWER_COLOURS: tuple[str, ...] = tuple(COLOURS)

# Spellings people use for the same palette colour.
SPELLINGS: dict[str, str] = {"grey": "gray"}


def canonical_colour(word: str) -> str | None:
    """The palette name for a colour word (case-insensitive, common spellings), or None."""
    w = word.strip().lower()
    w = SPELLINGS.get(w, w)
    return w if w in COLOURS else None


def rgba(name: str) -> list[float]:
    """The colour as an RGBA list for PyBullet."""
    return [*COLOURS[name], 1.0]
