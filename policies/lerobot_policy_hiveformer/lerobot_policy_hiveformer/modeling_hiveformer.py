"""HiveFormer (Guhur et al., "Instruction-driven history-aware policies for robotic manipulations",
CoRL 2022) as a LeRobot policy.

Per keyframe step every camera gives RGB, a world-frame point cloud (rebuilt here from depth in millimetres
and calibration) and a channel marking the current gripper position. A shared UNet encoder turns each camera
into a grid of tokens; a block-causal transformer mixes them with the instruction's CLIP token features
and with the tokens of earlier steps; a UNet decoder scores every pixel of every camera, and the
position is the softmax-weighted point cloud plus an offset; a small CNN predicts rotation and gripper.

Here: the policy LeRobot calls (`HiveformerPolicy`: losses, rollout cache), then the network (`HiveformerModel`).
Its parts stand alone: `observations.py` (inputs and geometry), `text_encoders.py`, `unet.py`, `attention.py`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from .attention import BlockCausalLayer, PackedSteps, block_causal_mask
from .configuration_hiveformer import ENCODER_STRIDE, HiveformerConfig
from .dataset_format import GRIPPER_STATE_DIM
from .observations import KeyframeObservations, keyframe_observations, take_steps
from .operations import PYTORCH, Operations, operations
from .text_encoders import CLIP_CONTEXT_LENGTH, COLOUR_FEATURES, InstructionEncoder, make_instruction_encoder
from .unet import ENCODER_CHANNELS, LEAKY_SLOPE, ConvBlock, UNetDecoder, UNetEncoder

# --- Policy ---------------------------------------------------------------------------------------


class HiveformerPolicy(PreTrainedPolicy):
    """HiveFormer keyframe policy: one action = the next keyframe's gripper pose and open command."""

    config_class = HiveformerConfig
    name = "hiveformer"

    def __init__(self, config: HiveformerConfig, dataset_stats=None, dataset_meta=None, **kwargs):
        super().__init__(config)
        config.validate_features()
        if config.text_encoder == "one_hot" and not config.instruction_vocabulary:
            if dataset_meta is None:
                raise ValueError(
                    "text_encoder='one_hot' needs instruction_vocabulary, or a dataset to read the "
                    "tasks from."
                )
            config.instruction_vocabulary = sorted(str(task) for task in dataset_meta.tasks.index)
        if config.n_history is None and config.use_history:
            if dataset_meta is None:
                raise ValueError("n_history is not set: pass it, or a dataset whose longest episode sets it.")
            config.n_history = longest_episode(dataset_meta)
        self.config = config
        # Kept outside the module tree: the frozen encoder is neither trained nor saved with the policy.
        self.instruction_encoder: InstructionEncoder = make_instruction_encoder(config)
        self.ops = operations(config.cpu_kernels)
        self.model = HiveformerModel(config, self.instruction_encoder.feature_dim, self.ops)
        self.reset()

    def get_optim_params(self) -> list[dict]:
        """Two AdamW groups, as in the authors' train.py: no weight decay on biases and normalisation
        layers, the preset's weight decay on everything else."""
        norms = {
            id(p)
            for module in self.modules()
            if isinstance(module, nn.LayerNorm | nn.GroupNorm)
            for p in module.parameters(recurse=False)
        }
        decayed, plain = [], []
        for name, p in self.named_parameters():
            if p.requires_grad:
                (plain if name.endswith("bias") or id(p) in norms else decayed).append(p)
        return [{"params": decayed}, {"params": plain, "weight_decay": 0.0}]

    def reset(self):
        """Forget the rollout history; call at every episode start."""
        self._history: deque[Tensor] = deque(maxlen=self.config.history_length)

    def _encode_instructions(self, instructions: list[str], device: torch.device) -> tuple[Tensor, Tensor]:
        features, mask = self.instruction_encoder.encode(instructions)
        if self.training and self.config.colour_word_dropout:
            features = drop_colour_words(features, self.config.colour_word_dropout)
        if not self.config.instruction_as_sequence:
            weights = mask.unsqueeze(-1).to(features.dtype)
            features = (features * weights).sum(1, keepdim=True) / weights.sum(1, keepdim=True)
            mask = mask[:, :1]
        return features.to(device), mask.to(device)

    def predict_keyframes(self, batch: dict) -> KeyframePrediction:
        """Predictions for every step of a batch with history (B, T, ...) or a single step (B, ...)."""
        obs = keyframe_observations(batch, self.config, build_maps=self.ops.keyframe_maps)
        instruction, instruction_mask = self._encode_instructions(obs.instructions, obs.points.device)
        return self.model(obs, instruction, instruction_mask)

    def forward(self, batch: dict) -> tuple[Tensor, dict]:
        """Teacher-forced losses over every non-padded step of the history window."""
        supervised = supervised_steps(batch)  # (B, T)
        target = window_targets(batch)  # (B, T, 8)
        config = self.config
        scales = (config.augmentation_min_scale, config.augmentation_max_scale)
        rescale = scales if self.training and scales != (1.0, 1.0) else None
        # no maps for padding steps
        obs = keyframe_observations(batch, config, keep=supervised, rescale=rescale, build_maps=self.ops.keyframe_maps)
        instruction, instruction_mask = self._encode_instructions(obs.instructions, obs.points.device)
        # The heads run on the supervised steps only: (M, ...) predictions for M supervised steps.
        prediction = self.model(obs, instruction, instruction_mask, decode=supervised)
        target = target[supervised]  # (M, 8)
        count = max(target.shape[0], 1)

        position_loss = ((prediction.position - target[:, :3]) ** 2).sum() / count
        rotation_loss = quaternion_loss(prediction.quaternion, target[:, 3:7]).sum() / count
        gripper_loss = (
            F.binary_cross_entropy_with_logits(prediction.open_logit, target[:, 7], reduction="sum") / count
        )
        loss = (
            self.config.position_loss_weight * position_loss
            + self.config.rotation_loss_weight * rotation_loss
            + self.config.gripper_loss_weight * gripper_loss
        )
        names = ["position_loss", "rotation_loss", "gripper_loss"]
        losses = [position_loss, rotation_loss, gripper_loss]
        if self.config.heatmap_loss_weight:
            heatmap_loss = heatmap_cross_entropy(
                prediction.pixel_logits, obs.pixels(obs.points, supervised), obs.pixels(obs.valid_pixels, supervised),
                target[:, :3], self.config.heatmap_loss_sigma,
            ).sum() / count
            loss = loss + self.config.heatmap_loss_weight * heatmap_loss
            names.append("heatmap_loss")
            losses.append(heatmap_loss)
        values = torch.stack([*losses, loss]).detach().tolist()  # one sync
        return loss, dict(zip([*names, "total_loss"], values, strict=True))

    @torch.inference_mode()
    def predict_action_chunk(self, batch: dict) -> Tensor:
        """(B, 1, 8): the next keyframe for the newest step, using and extending the rollout history."""
        if self.training:  # eval() walks every module (~1 ms a step): only when needed
            self.eval()
        obs = keyframe_observations(batch, self.config, build_maps=self.ops.keyframe_maps)
        current = _last_step(obs)
        everything = torch.ones_like(current.step_valid)  # (B, 1)
        # Only the newest step is encoded; earlier steps' tokens come from the rollout history.
        encoded = self.model.encode_steps(current, everything)
        self._history.append(encoded.tokens[:, 0])
        window = torch.stack(list(self._history), dim=1)  # (B, T', N, D)
        step_valid = torch.ones(window.shape[:2], dtype=torch.bool, device=window.device)
        instruction, instruction_mask = self._encode_instructions(obs.instructions, window.device)
        context = self.model.contextualise(
            window, step_valid, instruction, instruction_mask, last_step_only=True
        )  # (B, 1, N, D)
        prediction = self.model.decode_steps(context, encoded, current, everything)  # (B, ...)
        return prediction.action().unsqueeze(1)

    @torch.inference_mode()
    def select_action(self, batch: dict) -> Tensor:
        """(B, 8) = [x, y, z, qx, qy, qz, qw, open] for the current keyframe step."""
        return self.predict_action_chunk(batch)[:, 0]


def longest_episode(dataset_meta) -> int:
    """Frames of the longest episode of a `LeRobotDatasetMetadata`: the history a whole episode needs."""
    return int(max(dataset_meta.episodes["length"]))


def window_steps(batch: dict) -> int:
    """T: the observation steps of a training batch (1 without history)."""
    state = batch[OBS_STATE]
    return state.shape[1] if state.dim() == 3 else 1


def window_targets(batch: dict) -> Tensor:
    """(B, T, 8): the action target of each observation step (the look-back action left out)."""
    action = batch[ACTION]
    return (action if action.dim() == 3 else action.unsqueeze(1))[:, -window_steps(batch) :]


def supervised_steps(batch: dict) -> Tensor:
    """(B, T) bool: the steps of each window whose context is one a rollout produces.

    A rollout's window holds the episode from its first keyframe, or the last `T` keyframes. A training
    window that starts at the episode start gives every real step exactly its rollout context, so all of
    them are supervised (a whole-episode sample: every keyframe once). A window that starts later gives
    only its last step the rollout context; its earlier steps see a truncated history that no rollout
    produces, so they are not supervised (each of them is the last step of its own window).

    Whether a window starts at the episode start: the look-back action before it (the configuration's
    `action_delta_indices` start one step before the observations) is padding. Without it (a batch built
    with as many actions as observations), whether the window's first step is padding.
    """
    steps = window_steps(batch)
    pad = batch.get(OBS_STATE + "_is_pad")
    if pad is None or pad.dim() != 2:
        real = torch.ones(batch[OBS_STATE].shape[0], steps, dtype=torch.bool, device=batch[OBS_STATE].device)
    else:
        real = ~pad.bool()
    starts_at_episode_start = ~real[:, :1]  # (B, 1): padding before the first real step
    action_pad = batch.get(ACTION + "_is_pad")
    if action_pad is not None:
        action_pad = action_pad.bool() if action_pad.dim() == 2 else action_pad.bool().unsqueeze(1)
        if action_pad.shape[1] == steps + 1:
            starts_at_episode_start = action_pad[:, :1]
        real &= ~action_pad[:, -steps:]
    last = torch.arange(steps, device=real.device) == steps - 1
    return real & (starts_at_episode_start | last)


def _last_step(obs: KeyframeObservations) -> KeyframeObservations:
    last = torch.zeros_like(obs.pixel_steps)
    last[:, -1] = True
    return KeyframeObservations(
        stem=obs.pixels(obs.stem, last),
        points=obs.pixels(obs.points, last),
        valid_pixels=obs.pixels(obs.valid_pixels, last),
        patch_xyz=obs.pixels(obs.patch_xyz, last),
        calibration=obs.calibration[:, -1:],
        gripper=obs.gripper[:, -1:],
        step_valid=obs.step_valid[:, -1:],
        pixel_steps=obs.pixel_steps[:, -1:],
        instructions=obs.instructions,
    )


# --- Losses ---------------------------------------------------------------------------------------


def heatmap_cross_entropy(logits: Tensor, points: Tensor, valid: Tensor, target: Tensor, sigma: float) -> Tensor:
    """(M,) cross-entropy of the pixel attention (`logits` (M, C, H, W)) against the distribution over the valid
    pixels (`valid` (M, C, H, W)) of a Gaussian of each pixel's world point (`points` (M, C, 3, H, W)) distance to
    the target position (`target` (M, 3)), standard deviation `sigma` metres."""
    squared_distance = (points - target[:, None, :, None, None]).square().sum(2)  # (M, C, H, W)
    wanted = (-squared_distance / (2 * sigma**2)).masked_fill(~valid, float("-inf")).flatten(1).softmax(-1)
    log_attention = logits.flatten(1).log_softmax(-1).masked_fill(~valid.flatten(1), 0.0)  # 0 * log(0) = 0
    return -(wanted * log_attention).sum(-1)


def quaternion_loss(predicted: Tensor, target: Tensor) -> Tensor:
    """Squared error to the closer of q and -q (both describe the same rotation). (..., 4) -> (...)."""
    direct = ((predicted - target) ** 2).sum(-1)
    flipped = ((predicted + target) ** 2).sum(-1)
    return torch.minimum(direct, flipped)


def drop_colour_words(features: Tensor, probability: float) -> Tensor:
    """(B, L, D + 4) instruction features with `colour_features` -> the same with each colour token's text
    features (all but its last 4, the CIELAB coordinates and flag) zeroed with ``probability``."""
    colour_token = features[..., -1] > 0  # the flag
    dropped = colour_token & (torch.rand(colour_token.shape, device=features.device) < probability)
    text = features[..., :-COLOUR_FEATURES].masked_fill(dropped.unsqueeze(-1), 0.0)
    return torch.cat([text, features[..., -COLOUR_FEATURES:]], dim=-1)


# --- Network --------------------------------------------------------------------------------------


@dataclass
class KeyframePrediction:
    """Predictions for the decoded steps; `...` is (B, T) for a whole window or (M,) for selected steps."""

    position: Tensor  # (..., 3) world metres
    quaternion: Tensor  # (..., 4) unit, [qx, qy, qz, qw]
    open_logit: Tensor  # (...)
    pixel_attention: Tensor  # (..., C, H, W): softmax over all pixels of all cameras
    pixel_logits: Tensor  # (..., C, H, W): its logits (temperature applied; pixels without depth at the minimum)

    def action(self) -> Tensor:
        """(..., 8) = [x, y, z, qx, qy, qz, qw, open] with open thresholded to 0/1."""
        open_command = (self.open_logit > 0).to(self.position.dtype).unsqueeze(-1)
        return torch.cat([self.position, self.quaternion, open_command], dim=-1)

    def unflatten(self, lead: torch.Size) -> "KeyframePrediction":
        """(M, ...) -> (*lead, ...) where M is the product of `lead`, e.g. (B*T, 3) -> (B, T, 3)."""
        return KeyframePrediction(
            **{f.name: getattr(self, f.name).unflatten(0, lead) for f in fields(KeyframePrediction)}
        )


@dataclass
class EncodedSteps:
    tokens: Tensor  # (B, T, N, D) with N = C * grid cells + 1 gripper token; no step embedding yet
    encoded: Tensor  # (B, T) bool: the steps that went through the encoder (the others' patch features are 0)
    skips: list[Tensor]  # encoder features of the encoded steps in (b, t) order, each (M * C, 16, h, w)


class HiveformerModel(nn.Module):
    """The network; inputs are KeyframeObservations, outputs a KeyframePrediction per step."""

    def __init__(self, config: HiveformerConfig, instruction_feature_dim: int, ops: Operations = PYTORCH):
        super().__init__()
        self.config = config
        self.ops = ops
        dim = config.hidden_dim
        self.num_cameras = len(config.camera_names)
        height, width = config.image_shape
        self.grid = (height // ENCODER_STRIDE, width // ENCODER_STRIDE)

        # RGB (3) + gripper mark (1), as the authors; + the point cloud (3) with stem_point_cloud.
        self.encoder = UNetEncoder(7 if config.stem_point_cloud else 4, ops.group_norm_leaky_relu)
        self.patch_to_token = nn.Linear(ENCODER_CHANNELS + 3, dim)
        self.gripper_to_token = nn.Linear(GRIPPER_STATE_DIM, dim)
        self.instruction_to_token = nn.Linear(instruction_feature_dim, dim)
        if config.instruction_position_embeddings:
            self.instruction_position_embedding = nn.Embedding(CLIP_CONTEXT_LENGTH, dim)
        if config.instruction_layers:
            layer = nn.TransformerEncoderLayer(
                dim, config.num_heads, config.feedforward_dim, config.dropout, batch_first=True
            )
            self.instruction_layers = nn.TransformerEncoder(layer, config.instruction_layers, enable_nested_tensor=False)
        self.step_embedding = nn.Embedding(config.history_length, dim)
        # One embedding per camera, plus one for the gripper-state token.
        self.source_embedding = nn.Embedding(self.num_cameras + 1, dim)
        if config.use_position_embeddings:
            self.patch_row_embedding = nn.Embedding(self.grid[0], dim)
            if config.use_column_embeddings:
                self.patch_col_embedding = nn.Embedding(self.grid[1], dim)
        self.layers = nn.ModuleList([BlockCausalLayer(config) for _ in range(config.num_layers)])

        self.decoder = UNetDecoder(dim, ops.group_norm_leaky_relu, ops.bilinear_upsample)
        self.rotation_gripper_cnn = nn.Sequential(*(ConvBlock(dim, dim, norm=ops.group_norm_leaky_relu) for _ in range(2)))
        # Offset (3) + quaternion (4) + open logit (1), from pooled camera features + the gripper token.
        self.rotation_gripper_head = nn.Sequential(
            nn.Linear(2 * dim, dim), nn.LeakyReLU(LEAKY_SLOPE, inplace=True), nn.Linear(dim, 8)
        )
        # The offset starts at zero, as the authors' offset table does: at first the position is the
        # attention-weighted point of the cloud, so the pixel heatmap has to do the pointing.
        with torch.no_grad():
            self.rotation_gripper_head[-1].weight[:3].zero_()
            self.rotation_gripper_head[-1].bias[:3].zero_()

    @property
    def tokens_per_step(self) -> int:
        return self.num_cameras * self.grid[0] * self.grid[1] + 1

    def encode_steps(self, obs: KeyframeObservations, encode: Tensor) -> EncodedSteps:
        """Per-step tokens, independent of every other step (so they can be cached during rollouts).

        Only the steps where `encode` (B, T) is True go through the encoder; the others (history padding,
        which no step attends to) keep zero patch features.
        """
        batch, steps = encode.shape
        cameras = obs.points.shape[1]
        # (M*C, 4 or 7, H, W) viewed channels-last: oneDNN's convolutions with few channels run much faster on that
        # layout than on NCHW (which they reorder on every call), and every encoder and decoder feature map inherits it.
        images = obs.pixels(obs.stem, encode).flatten(0, 1).permute(0, 3, 1, 2)
        patch_xyz = obs.pixels(obs.patch_xyz, encode).flatten(0, 1)  # (M*C, 3, h, w)
        skips = self.encoder(images)
        bottleneck = skips[-1]  # (M*C, 16, h, w)

        # Joined channels-last, like every feature map, so that the gradients flowing back stay channels-last:
        # LeakyReLU's and GroupNorm's backward passes on a mix of layouts run ~8x slower.
        patch_features = torch.cat([bottleneck.permute(0, 2, 3, 1), patch_xyz.permute(0, 2, 3, 1)], dim=-1)
        patch_features = patch_features.flatten(1, 2)  # (M*C, hw, 19)
        patch_tokens = self.patch_to_token(patch_features).unflatten(0, (-1, cameras))  # (M, C, h*w, D)
        visual = patch_tokens.new_zeros(batch, steps, *patch_tokens.shape[1:])  # (B, T, C, h*w, D)
        visual = visual.index_put((encode,), patch_tokens)
        if self.config.use_position_embeddings:
            position = self.patch_row_embedding.weight[:, None, :].expand(-1, self.grid[1], -1)
            if self.config.use_column_embeddings:
                position = position + self.patch_col_embedding.weight[None, :, :]
            visual = visual + position.flatten(0, 1)
        visual = visual + self.source_embedding.weight[:cameras, None, :]
        gripper_token = self.gripper_to_token(obs.gripper) + self.source_embedding.weight[cameras]  # (B,T,D)
        tokens = torch.cat([visual.flatten(2, 3), gripper_token.unsqueeze(2)], dim=2)  # (B, T, N, D)
        return EncodedSteps(tokens=tokens, encoded=encode, skips=skips)

    def instruction_tokens(self, instruction: Tensor) -> Tensor:
        """Instruction features (B, L, F) -> the tokens the steps attend to (B, L, D)."""
        if self.config.instruction_feature_norm:  # padding tokens (all zeros) stay zeros
            instruction = F.layer_norm(instruction, instruction.shape[-1:])
        tokens = self.instruction_to_token(instruction)
        length = tokens.shape[1]
        if self.config.instruction_position_embeddings:
            tokens = tokens + self.instruction_position_embedding.weight[:length]
        if self.config.instruction_layers:  # padding comes after the real tokens, so no real token sees it
            causal = nn.Transformer.generate_square_subsequent_mask(length, device=tokens.device, dtype=tokens.dtype)
            tokens = self.instruction_layers(tokens, mask=causal, is_causal=True)
        return tokens

    def contextualise(
        self,
        tokens: Tensor,
        step_valid: Tensor,
        instruction: Tensor,
        instruction_mask: Tensor,
        last_step_only: bool = False,
    ) -> Tensor:
        """Block-causal transformer over a window. tokens (B, T, N, D) -> (B, T, N, D), zero at the padding
        steps (`step_valid` False), which take no part: the layers run on the real steps only, packed.

        With last_step_only, the last layer computes only the newest step's outputs -> (B, 1, N, D): the
        same values (earlier steps never see later ones), at a fraction of the cost during rollouts.
        """
        steps = tokens.shape[1]
        # Steps are numbered among the window's real keyframes, so a training window that starts before
        # the episode and a rollout at the same keyframe give each step the same embedding.
        ordinal = (step_valid.long().cumsum(1) - 1).clamp_min(0)
        x = tokens + self.step_embedding(ordinal).unsqueeze(2)
        instruction_tokens = self.instruction_tokens(instruction)
        layers = self.layers[:-1] if last_step_only else self.layers
        if layers:  # on the real steps only, packed; padding steps come back as zeros (nothing attends to them)
            packing = PackedSteps.of(step_valid)
            rows = packing.sample * steps + packing.step  # each packed step's row of the window's B*T steps
            packed = x.flatten(0, 1).index_select(0, rows)  # (M, N, D)
            for layer in layers if packing.counts else ():
                packed = layer.forward_packed(packed, instruction_tokens, instruction_mask, packing)
            x = x.new_zeros(x.flatten(0, 1).shape).index_copy(0, rows, packed).view(x.shape)
        if not last_step_only:
            return x
        allowed = block_causal_mask(step_valid, instruction_mask, x.shape[2], self.config.use_history,
                                    slice(steps - 1, steps))
        return self.layers[-1](x[:, -1:], instruction_tokens, allowed, history=x[:, :-1].flatten(1, 2))  # (B,1,N,D)

    def decode_steps(
        self, context: Tensor, encoded: EncodedSteps, obs: KeyframeObservations, decode: Tensor
    ) -> KeyframePrediction:
        """Heads for the steps where `decode` (B, T) is True (a subset of the encoded ones) -> (M, ...).

        `context` (B, T, N, D) and `obs` hold the same T steps as `encoded`.
        """
        dim = context.shape[-1]
        cameras = self.num_cameras
        grid_h, grid_w = self.grid
        decoded_among_encoded = decode[encoded.encoded]  # (M_encoded,) bool
        # Selected in the channels-last (N, h, w, 16) view, so the selection's gradient is channels-last too.
        skips = [
            take_steps(skip.permute(0, 2, 3, 1).unflatten(0, (-1, cameras)), decoded_among_encoded, 1)
            .flatten(0, 1)
            .permute(0, 3, 1, 2)
            for skip in encoded.skips
        ]  # each (M*C, 16, h, w)
        step_context = take_steps(context, decode)  # (M, N, D)
        camera_grids = (
            step_context[:, :-1].reshape(-1, grid_h, grid_w, dim).permute(0, 3, 1, 2)
        )  # (M*C, D, h, w)
        logits = self.decoder(camera_grids, skips)  # (M*C, H, W)
        height, width = logits.shape[-2:]
        logits = logits.view(-1, cameras * height * width) / self.config.attention_temperature
        valid = obs.pixels(obs.valid_pixels, decode).view(logits.shape)  # (M, C*H*W)
        # Pixels without depth have no 3D point to point at (`where`: masked_fill's values and gradient in one pass).
        logits = torch.where(valid, logits, torch.finfo(logits.dtype).min)
        attention = logits.softmax(-1).view(-1, cameras, height, width)  # (M, C, H, W)
        logits = logits.view(attention.shape)
        # sum over cameras and pixels of attention * point: (M, C, 3, H*W) @ (M, C, H*W, 1), no copy of the points
        points = obs.pixels(obs.points, decode).flatten(-2)
        attended_point = self.ops.weighted_points(points, attention.flatten(-2).unsqueeze(-1)).squeeze(-1).sum(1)  # (M, 3)

        pooled = self.rotation_gripper_cnn(camera_grids).amax(dim=(-2, -1))  # (M*C, D)
        pooled = pooled.view(-1, cameras, dim).amax(dim=1)  # (M, D)
        head = self.rotation_gripper_head(torch.cat([pooled, step_context[:, -1]], dim=-1))  # (M, 8)
        return KeyframePrediction(
            position=attended_point + head[:, :3],
            quaternion=F.normalize(head[:, 3:7], dim=-1),
            open_logit=head[:, 7],
            pixel_attention=attention,
            pixel_logits=logits,
        )

    def forward(
        self,
        obs: KeyframeObservations,
        instruction: Tensor,
        instruction_mask: Tensor,
        decode: Tensor | None = None,
    ) -> KeyframePrediction:
        """Predictions for every step -> (B, T, ...), or for the steps where `decode` (B, T) -> (M, ...).

        The encoder runs on the real steps (which the decoded ones attend to) and the decoded ones only:
        padding steps are left out of the transformer, so encoding them would change nothing (a decoded
        padding step gets a zero context). The heads run on
        the decoded steps only, as the authors' code runs them on the unpadded steps only.
        """
        decode_all = decode is None
        if decode_all:
            decode = torch.ones_like(obs.step_valid)
        encoded = self.encode_steps(obs, obs.step_valid | decode)
        context = self.contextualise(encoded.tokens, obs.step_valid, instruction, instruction_mask)
        prediction = self.decode_steps(context, encoded, obs, decode)
        if decode_all:
            prediction = prediction.unflatten(obs.step_valid.shape)
        return prediction
