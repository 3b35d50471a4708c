"""Push button: press the one instructed coloured button; the other buttons are distractors."""

from __future__ import annotations

from demo_factory.tasks.push_buttons import PushButtons
from demo_factory.tasks.variations import Variation


class PushButton(PushButtons):
    """Push buttons' scene with a single instructed colour: success is exactly that one press."""

    name = "push_button"
    description = "Press the instructed coloured button once; two other buttons are distractors."
    categories = ("rotation-invariant",)
    max_sequence = 1
    n_train = n_test = 9
    split_seed = 20220302
    paper_numbering = None  # not one of the paper's numbered tasks: its 18 colours are dealt at random

    def synthetic_instructions(self, variation: Variation) -> list[str]:
        c = variation.words[0]
        return [f"push the {c} button", f"press the {c} button", f"press down on the {c} button"]
