"""Instructions: colour-word corruption and human-written instruction files.

Owns the corrupted-instruction rewriting (`corruption`) and the human-instruction file format (`human`:
JSONL rows or the HiveFormer authors' ``annotations.json``, shipped in ``data/hiveformer/`` with its
licence). Reads those files; writes nothing (``collect`` appends rows).
"""

from demo_factory.instructions.corruption import COLOUR_SYNONYMS, colour_words, corrupt_instruction
from demo_factory.instructions.human import (
    HumanInstruction,
    HumanInstructionError,
    assign_human_instructions,
    hiveformer_annotations,
    load_human_instructions,
    shipped_human_instructions,
)

__all__ = [
    "COLOUR_SYNONYMS",
    "HumanInstruction",
    "HumanInstructionError",
    "assign_human_instructions",
    "colour_words",
    "corrupt_instruction",
    "hiveformer_annotations",
    "load_human_instructions",
    "shipped_human_instructions",
]
