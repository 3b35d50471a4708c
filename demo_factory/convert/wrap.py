"""The dataset card's line lengths: paragraphs filled, long shell commands continued.

The card reads as well in a terminal or a diff as on the Hub: each paragraph and list item is filled to the
template's own width (Markdown joins the lines of a paragraph again, so what the template and the generated
text say renders the same), and a shell command in a ``bash`` block is split before its options with ``\\``
continuations. Table rows, headings, the YAML front matter and other code blocks cannot be wrapped without
changing what they mean: the code that writes them keeps them short.
"""

from __future__ import annotations

import re
import shlex

WIDTH = 110  # the template's prose lines are at most this long
LIST_ITEM = re.compile(r"\s*(?:[-*+]|\d{1,9}[.)])\s+")
# A word that would open a block (list item, heading, quote, table row, rule, setext underline, fence)
# were it the first of a line: never wrapped onto a line of its own.
OPENS_BLOCK = re.compile(r"(?:[-*+]|#{1,6}|\d{1,9}[.)]|=+|-+|>.*|\|.*|```.*|~~~.*)")
JOINS = ("→", "/", "=")  # never cut from the words either side: "red → scarlet", "open 1 / closed 0", "`fps` = 10"
SHELL_FENCES = ("```bash", "```sh", "```shell", "```console")


def wrap_card(text: str, width: int = WIDTH) -> str:
    """``text`` (a card: YAML front matter, then Markdown) with each paragraph and list item filled to ``width``
    and each shell command wider than that continued over lines."""
    lines = text.split("\n")
    out: list[str] = []
    block: list[str] = []  # the lines of the paragraph or list item being read, or of the code block
    fence = None  # the line that opened the code block being read
    front_matter = lines[0] == "---"
    for i, line in enumerate(lines):
        stripped = line.strip()
        if front_matter:
            front_matter = i == 0 or stripped != "---"
            out.append(line)
        elif fence is not None and stripped != fence[:3]:
            block.append(line)
        elif fence is not None:  # the block's closing fence
            if fence in SHELL_FENCES:
                block = [part for command in join_continued(block) for part in wrap_command(command, width)]
            out += [*block, line]
            block, fence = [], None
        elif not stripped or stripped.startswith(("|", "#", "<", "![", "```", "~~~")) or LIST_ITEM.match(line):
            out += _fill(block, width)
            block = []
            if stripped.startswith(("```", "~~~")):
                fence = stripped
                out.append(line)
            elif LIST_ITEM.match(line):
                block = [line]
            else:
                out.append(line)
        else:
            block.append(line)
    return "\n".join(out + (_fill(block, width) if fence is None else block))


def _fill(lines: list[str], width: int) -> list[str]:
    """The lines of one paragraph or list item, joined and wrapped again."""
    if not lines:
        return []
    return wrap_prose(" ".join([lines[0].rstrip(), *(line.strip() for line in lines[1:])]), width)


def wrap_prose(line: str, width: int = WIDTH) -> list[str]:
    """A Markdown line as lines of at most ``width`` characters where its words allow: a list item's
    continuation lines are indented under its text, and no line starts with a word that would open a block."""
    if len(line) <= width:
        return [line]
    item = LIST_ITEM.match(line)
    indent = len(line) - len(line.lstrip())
    follow = " " * (item.end() if item else indent)
    # split at single spaces between words only, so that runs of spaces (in code spans) stay as they are
    words = re.split(r"(?<=\S) (?=\S)", line[indent:])
    units: list[str] = []  # runs of words that no line break may cut
    for before, word in zip(["", *words], words):
        if units and (word in JOINS or before in JOINS or OPENS_BLOCK.fullmatch(word)):
            units[-1] += " " + word
        else:
            units.append(word)
    lines, current = [], line[:indent] + units[0]
    for unit in units[1:]:
        if len(current) + 1 + len(unit) <= width:
            current += " " + unit
        else:
            lines.append(current)
            current = follow + unit
    return [*lines, current]


def shell_words(line: str) -> list[str]:
    """``line`` cut at the spaces outside quotes, each word as written (its quotes kept)."""
    lexer = shlex.shlex(line, posix=False)
    lexer.whitespace_split, lexer.commenters = True, ""
    return list(lexer)


def wrap_command(line: str, width: int = WIDTH) -> list[str]:
    """A shell command as lines of at most ``width`` characters where it allows: cut only before an option,
    so that each option stays with its values, each line but the last ending in `` \\``."""
    if len(line) <= width or line.lstrip().startswith("#") or line.rstrip().endswith("\\"):
        return [line]
    indent = line[:len(line) - len(line.lstrip())]
    parts: list[str] = []  # the command with its first arguments, then each option with its values
    for word in shell_words(line):
        if word.startswith("-") or not parts:
            parts.append(word)
        else:
            parts[-1] += " " + word
    lines, current = [], indent + parts[0]
    for part in parts[1:]:
        if len(current) + 1 + len(part) + 2 > width and current != indent + parts[0]:
            lines.append(current + " \\")
            current = indent + "  " + part
        else:
            current += " " + part
    return [*lines, current]


def join_continued(lines: list[str]) -> list[str]:
    """Shell lines with their `` \\`` continuations joined: one line per command."""
    joined: list[str] = []
    continued = False
    for line in lines:
        if continued:
            joined[-1] += " " + line.strip()
        else:
            joined.append(line)
        continued = joined[-1].endswith("\\")
        if continued:
            joined[-1] = joined[-1][:-1].rstrip()
    return joined
