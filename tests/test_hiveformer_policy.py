"""HiveFormer policy plugin on a tiny keyframe dataset written in the converter's format."""

import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hiveformer_fixtures import (
    EPISODE_LENGTHS,
    history_batch,
    tiny_config,
    tiny_dataset_root,
    write_tiny_dataset,
)
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot_policy_hiveformer import HiveformerConfig, HiveformerPolicy, observations
from lerobot_policy_hiveformer import attention as attention_module
from lerobot_policy_hiveformer.attention import (
    BlockCausalLayer,
    Dropout,
    MultiHeadAttention,
    PackedSteps,
    block_causal_mask,
)
from lerobot_policy_hiveformer.modeling_hiveformer import heatmap_cross_entropy, quaternion_loss, supervised_steps
from lerobot_policy_hiveformer.observations import (
    KeyframeObservations,
    gripper_pixel,
    keyframe_observations,
    patch_mean_points,
    project_to_pixels,
)
from lerobot_policy_hiveformer.text_encoders import ClipInstructionEncoder, tiny_random_clip_text_model
from lerobot_policy_hiveformer.unet import LEAKY_SLOPE, ConvBlock, conv_block_of_concatenation, upsample_twice

# The compiled CPU loops (the `cpu` extra); their tests are skipped without numba.
try:
    from lerobot_policy_hiveformer import cpu_kernels
except ImportError:
    cpu_kernels = None
needs_numba = pytest.mark.skipif(cpu_kernels is None, reason="the compiled CPU loops need numba (the `cpu` extra)")

__all__ = ["tiny_dataset_root"]  # the fixture is used by name

EPISODE_STARTS = [sum(EPISODE_LENGTHS[:i]) for i in range(len(EPISODE_LENGTHS))]


def make_tiny_policy(root, **overrides) -> HiveformerPolicy:
    config, meta = tiny_config(root, **overrides)
    return make_policy(config, ds_meta=meta)


def single_step(batch: dict, step: int) -> dict:
    """The observation of history step `step` as a rollout would deliver it: (B, ...) without time."""
    single = {}
    for key, value in batch.items():
        if key.startswith("observation.") and not key.endswith("_is_pad"):
            single[key] = value[:, step]
    single["task"] = batch["task"]
    return single


def test_point_cloud_rebuilds_the_table_plane(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root)
    obs = keyframe_observations(history_batch(tiny_dataset_root, config, [0, 7]), config)
    heights = obs.points[:, :, 2][obs.valid_pixels]  # every hit is on the table z = 0
    assert obs.valid_pixels.float().mean() > 0.5
    assert heights.abs().max() < 2e-3


def test_gripper_mark_peaks_at_the_projected_gripper(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root)
    obs = keyframe_observations(history_batch(tiny_dataset_root, config, [3]), config)
    calibration = obs.calibration[0, -1, 0]  # left shoulder camera
    points = obs.points.unflatten(0, obs.pixel_steps.shape)  # every step kept: (B, T, C, 3, H, W)
    point = points[0, -1, 0, :, 20, 11]  # the table point seen at row 20, column 11
    uv, in_front = project_to_pixels(point, calibration)
    assert in_front and torch.allclose(uv, torch.tensor([11.0, 20.0]), atol=0.1)
    assert gripper_pixel(point, calibration, 32, 32) == 20 * 32 + 11  # one pixel, as the authors'
    assert gripper_pixel(2 * calibration[4:].view(4, 4)[:3, 3] - point, calibration, 32, 32) == -1  # behind
    off_image = point + torch.tensor([5.0, 0.0, 0.0])  # far to the side
    uv, _ = project_to_pixels(off_image, calibration)
    assert not (0 <= uv[0] < 32 and 0 <= uv[1] < 32)
    assert gripper_pixel(off_image, calibration, 32, 32) == -1  # nothing marked at the border
    marked = obs.stem[..., -1].flatten(-2).sum(-1)  # (M, C): one pixel where the gripper is seen, none elsewhere
    assert set(marked.unique().tolist()) <= {0.0, 1.0} and marked.sum() > 0


def test_the_tokenizer_is_clips_and_needs_no_download():
    encoder = ClipInstructionEncoder(tiny_random_clip_text_model())
    tokens = encoder.tokenizer(["a photo of a cat"], context_length=77)[0]
    # The ids openai/clip-vit-base-patch32's tokenizer gives (start, words, end).
    assert tokens[:7].tolist() == [49406, 320, 1125, 539, 320, 2368, 49407]
    features, mask = encoder.encode(["a photo of a cat", "push the maroon button", "a photo of a cat"])
    assert features.shape == (3, 7, 64) and mask.sum(1).tolist() == [7, 6, 7]
    assert torch.equal(features[0], features[2])


def test_output_shapes(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [0, 6, 12])
    with torch.no_grad():
        prediction = policy.predict_keyframes(batch)
    assert prediction.position.shape == (3, 3, 3)
    assert prediction.quaternion.shape == (3, 3, 4)
    assert torch.allclose(prediction.quaternion.norm(dim=-1), torch.ones(3, 3))
    assert prediction.open_logit.shape == (3, 3)
    assert prediction.pixel_attention.shape == (3, 3, 3, 32, 32)
    assert torch.allclose(prediction.pixel_attention.sum(dim=(2, 3, 4)), torch.ones(3, 3))
    action = policy.select_action(single_step(batch, -1))
    assert action.shape == (3, 8) and set(action[:, 7].tolist()) <= {0.0, 1.0}


def test_later_steps_do_not_change_earlier_predictions(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [7])  # episode 1, keyframes 1..3: no padding
    assert not batch["observation.state_is_pad"].any()
    changed = dict(batch)
    for key in ("observation.images.wrist", "observation.images.left_shoulder", "observation.state"):
        changed[key] = batch[key].clone()
        changed[key][:, -1] = torch.rand_like(changed[key][:, -1])
    with torch.no_grad():
        original, perturbed = policy.predict_keyframes(batch), policy.predict_keyframes(changed)
    assert torch.equal(original.position[:, :-1], perturbed.position[:, :-1])
    assert torch.equal(original.quaternion[:, :-1], perturbed.quaternion[:, :-1])
    assert not torch.allclose(original.position[:, -1], perturbed.position[:, -1])


@pytest.mark.parametrize("masked", [False, True])
def test_attention_padded_to_the_fast_head_dimension_gives_the_same_outputs(monkeypatch, masked):
    """On CPU, heads narrower than 16 are zero-padded for PyTorch's fused kernel where no gradient is taken
    (rollouts); the outputs must be the unpadded attention's (the paper's 64 wide, 8 heads: head dimension 8).
    Training, where the padding costs more than it saves, keeps the heads as they are."""
    torch.manual_seed(0)
    attention = MultiHeadAttention(dim=64, num_heads=8, dropout=0.0)
    queries, keys = torch.randn(2, 30, 64), torch.randn(2, 90, 64)
    allowed = torch.rand(2, 1, 30, 90) > 0.3 if masked else None
    if masked:
        allowed[..., 0] = True  # every query sees at least one key
    with torch.no_grad():
        assert attention._heads(attention.query(queries)).shape[-1] == 16
        padded = attention(queries, keys, allowed)
        monkeypatch.setattr(attention_module, "FUSED_CPU_MIN_HEAD_DIM", 0)
        assert attention._heads(attention.query(queries)).shape[-1] == 8
        plain = attention(queries, keys, allowed)
    assert torch.allclose(padded, plain, atol=1e-6)
    monkeypatch.undo()
    assert attention._heads(attention.query(queries.requires_grad_())).shape[-1] == 8


@pytest.mark.parametrize("use_history", [True, False])
def test_packed_layer_equals_the_masked_layer_on_the_real_steps(use_history):
    """The training path runs each layer on the real steps only, one attention call per step ordinal
    (`BlockCausalLayer.forward_packed`); its outputs and gradients (inputs' and parameters') must be the
    masked layer's on the same window, whatever the padding of each sample (none, some, all but one step,
    every step) and of its instruction."""
    torch.manual_seed(0)
    config = HiveformerConfig(device="cpu", text_encoder="one_hot", attention_dropout=0.0, dropout=0.0,
                              n_history=6, use_history=use_history)
    layer = BlockCausalLayer(config)
    tokens, instruction = torch.randn(6, 6, 7, 64), torch.randn(6, 3, 64)
    step_valid = torch.tensor([[0, 0, 1, 1, 1, 1], [1] * 6, [0] * 6, [0, 0, 0, 0, 0, 1], [0, 1, 1, 1, 1, 1],
                               [0, 0, 0, 1, 1, 1]]).bool()
    instruction_mask = torch.tensor([[1, 1, 0], [1, 1, 1], [1, 1, 1], [1, 0, 0], [1, 1, 1], [1, 1, 0]]).bool()
    packing = PackedSteps.of(step_valid)
    assert packing.counts == [5, 4, 4, 3, 2, 1]
    weights = torch.linspace(-1, 1, int(step_valid.sum()) * 7 * 64).view(-1, 7, 64)

    def outputs_and_gradients(packed: bool):
        layer.zero_grad()
        x, words = tokens.clone().requires_grad_(), instruction.clone().requires_grad_()
        if packed:
            out = layer.forward_packed(x[packing.sample, packing.step], words, instruction_mask, packing)
        else:
            allowed = block_causal_mask(step_valid, instruction_mask, 7, use_history, slice(None))
            out = layer(x, words, allowed)[packing.sample, packing.step]
        (out * weights).sum().backward()
        return [out.detach(), x.grad, words.grad, *(p.grad for p in layer.parameters())]

    for packed, masked in zip(outputs_and_gradients(True), outputs_and_gradients(False), strict=True):
        assert torch.allclose(packed, masked, rtol=1e-4, atol=1e-5)  # sums over other orders


def test_world_points_are_the_camera_points_rotated_and_translated():
    """depth_to_world_points (built as depth x ray + translation) against R @ [(u-cx) d/fx, (v-cy) d/fy, d] + t
    with a rotation that mixes every axis."""
    torch.manual_seed(0)
    rotation = torch.linalg.qr(torch.randn(2, 3, 3)).Q
    world_from_camera = torch.eye(4).repeat(2, 1, 1)
    world_from_camera[:, :3, :3], world_from_camera[:, :3, 3] = rotation, torch.randn(2, 3)
    intrinsics = torch.tensor([[50.0, 60.0, 15.5, 11.0], [40.0, 45.0, 14.0, 12.5]])
    calibration = torch.cat([intrinsics, world_from_camera.flatten(1)], dim=1)  # (2, 20)
    depth = torch.rand(2, 24, 32) + 0.5
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    fx, fy, cx, cy = (intrinsics[:, i, None, None] for i in range(4))
    camera = torch.stack([(u - cx) * depth / fx, (v - cy) * depth / fy, depth], dim=1)  # (2, 3, H, W)
    expected = torch.einsum("bij,bjhw->bihw", rotation, camera) + world_from_camera[:, :3, 3, None, None]
    assert torch.allclose(observations.depth_to_world_points(depth, calibration), expected, atol=1e-5)


def test_quaternion_loss_is_sign_invariant(tiny_dataset_root):
    q = torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    predicted = torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    assert torch.allclose(quaternion_loss(predicted, q), quaternion_loss(predicted, -q))
    assert torch.allclose(quaternion_loss(q, -q), torch.zeros(5))

    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [2, 9])
    flipped = dict(batch)
    flipped["action"] = batch["action"].clone()
    flipped["action"][..., 3:7] *= -1
    with torch.no_grad():
        _, losses = policy.forward(batch)
        _, flipped_losses = policy.forward(flipped)
    assert losses["rotation_loss"] == pytest.approx(flipped_losses["rotation_loss"], rel=1e-6)
    assert set(losses) == {"position_loss", "rotation_loss", "gripper_loss", "total_loss"}


def test_padded_history_steps_are_ignored(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [0])  # first keyframe: two padded steps
    assert batch["observation.state_is_pad"][0].tolist() == [True, True, False]
    changed = dict(batch)
    changed["action"] = batch["action"].clone()
    changed["action"][:, :2] += 10.0
    changed["observation.images.wrist"] = batch["observation.images.wrist"].clone()
    changed["observation.images.wrist"][:, :2] = 0.5
    with torch.no_grad():
        loss, _ = policy.forward(batch)
        changed_loss, _ = policy.forward(changed)
    assert torch.allclose(loss, changed_loss)


@pytest.mark.parametrize("num_layers", [1, 2])
def test_select_action_with_its_own_history_matches_training_windows(tiny_dataset_root, num_layers):
    policy = make_tiny_policy(tiny_dataset_root, num_layers=num_layers).eval()
    start, length = EPISODE_STARTS[3], EPISODE_LENGTHS[3]
    windows = history_batch(tiny_dataset_root, policy.config, list(range(start, start + length)))
    with torch.no_grad():
        expected = policy.predict_keyframes(windows).action()[:, -1]  # (length, 8)
    policy.reset()
    for step in range(length):
        observation = {k: v[step : step + 1] for k, v in single_step(windows, -1).items() if k != "task"}
        observation["task"] = windows["task"][step : step + 1]
        action = policy.select_action(observation)
        assert torch.allclose(action[0], expected[step], atol=1e-5), step


def test_tiny_model_overfits_a_few_episodes(tiny_dataset_root):
    torch.manual_seed(0)
    no_augmentation = {"augmentation_min_scale": 1.0, "augmentation_max_scale": 1.0}
    policy = make_tiny_policy(tiny_dataset_root, n_history=2, **no_augmentation).train()
    batch = history_batch(tiny_dataset_root, policy.config, range(sum(EPISODE_LENGTHS[:2])))
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=3e-3)
    losses = []
    for _ in range(150):
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        if losses[-1] < losses[0] / 10:
            break
    assert math.isfinite(losses[-1])
    assert losses[-1] < losses[0] / 10, (len(losses), losses[0], losses[-5:])


def test_save_and_load_give_identical_outputs(tiny_dataset_root, tmp_path):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [4, 11])
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=None)
    policy.save_pretrained(tmp_path)
    preprocessor.save_pretrained(tmp_path)
    postprocessor.save_pretrained(tmp_path)

    reloaded = HiveformerPolicy.from_pretrained(tmp_path)
    reloaded_pre, reloaded_post = make_pre_post_processors(reloaded.config, pretrained_path=str(tmp_path))
    assert [step.__class__ for step in reloaded_pre.steps] == [step.__class__ for step in preprocessor.steps]
    with torch.no_grad():
        original = policy.predict_keyframes(batch)
        loaded = reloaded.predict_keyframes(reloaded_pre(batch))
    assert torch.equal(original.position, loaded.position)
    assert torch.equal(original.quaternion, loaded.quaternion)
    assert torch.equal(original.open_logit, loaded.open_logit)


@pytest.mark.parametrize(
    "ablation",
    [
        {"use_history": False},
        {"instruction_as_sequence": False},
        {"text_encoder": "one_hot"},
        {"use_position_embeddings": False},
        {"use_column_embeddings": False},
        {"instruction_position_embeddings": False},
        {"stem_point_cloud": True},
        {"instruction_layers": 1},
        {"instruction_feature_norm": True},
        {"heatmap_loss_weight": 0.1},
    ],
)
def test_ablations_train_and_act(tiny_dataset_root, ablation):
    policy = make_tiny_policy(tiny_dataset_root, **ablation)
    if "use_column_embeddings" in ablation:  # E_x left out alone: the row embedding E_y stays
        assert not hasattr(policy.model, "patch_col_embedding") and hasattr(policy.model, "patch_row_embedding")
    expected_steps = 1 if ablation.get("use_history") is False else 3
    assert policy.config.observation_delta_indices == list(range(1 - expected_steps, 1))
    batch = history_batch(tiny_dataset_root, policy.config, [1, 8])
    loss, _ = policy.forward(batch)
    loss.backward()
    assert math.isfinite(loss.item())
    if ablation.get("text_encoder") == "one_hot":
        assert policy.config.instruction_vocabulary == sorted(
            ["push the maroon button", "stack 2 navy blocks"]
        )
    assert policy.select_action(single_step(batch, -1)).shape == (2, 8)


def test_the_stem_sees_rgb_and_the_gripper_mark_as_the_authors_unless_told(tiny_dataset_root):
    """4 channels (RGB + mark) by default; xyz reaches the tokens through each patch's mean point. With
    stem_point_cloud the 7-channel input (RGB, world xyz, mark)."""
    assert make_tiny_policy(tiny_dataset_root).model.encoder.stem[0].in_channels == 4
    assert make_tiny_policy(tiny_dataset_root, stem_point_cloud=True).model.encoder.stem[0].in_channels == 7


@pytest.mark.parametrize("positions", [True, False])
def test_instruction_token_order_matters_only_with_position_embeddings(tiny_dataset_root, positions):
    """Cross-attention alone is blind to the order of the instruction tokens; the learned position
    embeddings are what tell "red, then blue" from "blue, then red"."""
    policy = make_tiny_policy(tiny_dataset_root, instruction_position_embeddings=positions).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [2, 8])
    obs = keyframe_observations(batch, policy.config)
    features, mask = policy._encode_instructions(obs.instructions, torch.device("cpu"))
    tokens = policy.model.encode_steps(obs, obs.step_valid).tokens
    length = int(mask[0].sum())
    reversed_features = features.clone()
    reversed_features[0, :length] = features[0, :length].flip(0)
    with torch.no_grad():
        plain = policy.model.contextualise(tokens, obs.step_valid, features, mask)
        reordered = policy.model.contextualise(tokens, obs.step_valid, reversed_features, mask)
    assert torch.allclose(plain[1], reordered[1])  # the other sample's instruction is unchanged
    assert torch.allclose(plain[0], reordered[0], atol=1e-5) is not positions


def test_instruction_layers_give_each_token_the_words_before_it_only(tiny_dataset_root):
    """With instruction_layers, a token's features change with the words before it (even without position
    embeddings) and never with the words after it: causal, as CLIP's text transformer."""
    policy = make_tiny_policy(tiny_dataset_root, instruction_layers=1, instruction_position_embeddings=False).eval()
    features = torch.randn(1, 6, policy.model.instruction_to_token.in_features)
    changed_last, changed_first = features.clone(), features.clone()
    changed_last[0, -1] += 1.0
    changed_first[0, 0] += 1.0
    with torch.no_grad():
        plain, late, early = (policy.model.instruction_tokens(x) for x in (features, changed_last, changed_first))
    assert torch.allclose(plain[0, :-1], late[0, :-1], atol=1e-6)
    assert not torch.allclose(plain[0, -1], late[0, -1], atol=1e-4)
    assert all(not torch.allclose(plain[0, i], early[0, i], atol=1e-4) for i in range(1, 6))


def test_instruction_feature_norm_projects_each_token_standardised(tiny_dataset_root):
    """With instruction_feature_norm each token's features are standardised before their projection: scaling or
    shifting them changes nothing, and features as small as minilm_words' (~0.06) weigh as much as unit ones.
    Padding tokens (all zeros) stay zeros."""
    model = make_tiny_policy(tiny_dataset_root, instruction_feature_norm=True).eval().model
    projection = model.instruction_to_token
    features = 0.06 * torch.randn(1, 5, projection.in_features)
    features[0, -1] = 0.0  # padding
    positions = model.instruction_position_embedding.weight[:5]
    with torch.no_grad():
        tokens, rescaled = model.instruction_tokens(features), model.instruction_tokens(10 * features + 0.5)
        variance = features.var(-1, unbiased=False, keepdim=True)
        standardised = (features - features.mean(-1, keepdim=True)) / (variance + 1e-5).sqrt()  # layer_norm's eps
        assert torch.allclose(tokens[0, :-1], (projection(standardised) + positions)[0, :-1], atol=1e-5)
        assert torch.allclose(tokens[0, -1], projection.bias + positions[-1])
        assert torch.allclose(tokens, rescaled, rtol=1e-2, atol=1e-2)  # equal but for eps against the variance
        content, raw_content = (tokens - positions - projection.bias), (projection(features) - projection.bias)
        assert content[0, :-1].std() > 10 * raw_content[0, :-1].std()


def test_heatmap_cross_entropy_targets_the_valid_pixels_nearest_the_target():
    """Against a target at one pixel's point and a narrow Gaussian, the loss is that pixel's cross-entropy; a pixel
    without depth takes no part even where its (zero) point is the target; the gradient raises the pixels near
    the target and lowers the others."""
    points = torch.zeros(1, 2, 3, 2, 2)
    points[0, :, 0] = torch.arange(8.0).view(2, 2, 2) / 10  # x = 0.0 ... 0.7 m
    valid = torch.ones(1, 2, 2, 2, dtype=torch.bool)
    valid[0, 0, 0, 0] = False  # x = 0.0, where the second target is
    logits = torch.randn(1, 2, 2, 2, requires_grad=True)
    near_pixel_3 = torch.tensor([[0.3, 0.0, 0.0]])
    loss = heatmap_cross_entropy(logits, points, valid, near_pixel_3, sigma=0.01)
    assert torch.allclose(loss, torch.nn.functional.cross_entropy(logits.view(1, -1), torch.tensor([3])))
    (gradient,) = torch.autograd.grad(loss.sum(), logits)
    assert gradient.view(-1)[3] < 0 and (gradient.view(-1)[[1, 2, 4, 5, 6, 7]] > 0).all()
    masked_logits = logits.detach().masked_fill(~valid, torch.finfo(logits.dtype).min)
    at_invalid_pixel = heatmap_cross_entropy(masked_logits, points, valid, torch.zeros(1, 3), sigma=0.01)
    assert torch.allclose(at_invalid_pixel, torch.nn.functional.cross_entropy(masked_logits.view(1, -1), torch.tensor([1])))


def test_heatmap_loss_is_added_to_the_total_only_when_weighted(tiny_dataset_root):
    batch = history_batch(tiny_dataset_root, make_tiny_policy(tiny_dataset_root).config, [1, 8])
    torch.manual_seed(0)
    _, plain = make_tiny_policy(tiny_dataset_root).eval().forward(batch)
    torch.manual_seed(0)
    _, weighted = make_tiny_policy(tiny_dataset_root, heatmap_loss_weight=0.5).eval().forward(batch)
    assert "heatmap_loss" not in plain and weighted["heatmap_loss"] > 0
    assert weighted["position_loss"] == pytest.approx(plain["position_loss"])
    assert weighted["total_loss"] == pytest.approx(plain["total_loss"] + 0.5 * weighted["heatmap_loss"])
    with pytest.raises(ValueError, match="heatmap_loss_sigma > 0, got 0.1 and 0.0"):
        HiveformerConfig(heatmap_loss_weight=0.1, heatmap_loss_sigma=0.0, device="cpu")


def test_n_history_defaults_to_the_longest_episode_of_the_dataset(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root, n_history=None)
    assert policy.config.n_history == max(EPISODE_LENGTHS)
    config, _ = tiny_config(tiny_dataset_root, n_history=None)
    with pytest.raises(ValueError, match="n_history is not set"):
        config.observation_delta_indices  # noqa: B018 (the property raises)


def test_missing_depth_feature_is_named(tmp_path):
    root = tmp_path / "no_wrist_depth"
    write_tiny_dataset(root, episode_lengths=(2,), drop_features=("observation.depth.wrist",))
    config, meta = tiny_config(root)
    with pytest.raises(ValueError, match=r"observation\.depth\.wrist"):
        make_policy(config, ds_meta=meta)


def test_clip_without_weights_says_how_to_point_to_a_local_copy(tiny_dataset_root, tmp_path):
    for path in (tmp_path / "missing", tmp_path):
        with pytest.raises(OSError, match="--policy.text_encoder_path"):
            make_tiny_policy(tiny_dataset_root, text_encoder="clip", text_encoder_path=str(path))


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="text_encoder"):
        HiveformerConfig(text_encoder="bert", device="cpu")
    with pytest.raises(ValueError, match="num_heads"):
        HiveformerConfig(hidden_dim=60, num_heads=8, device="cpu")
    with pytest.raises(ValueError, match="IDENTITY"):
        HiveformerConfig(normalization_mapping={"STATE": "MEAN_STD"}, device="cpu")
    with pytest.raises(ValueError, match="lr_schedule must be one of constant, cosine, constant_then_cosine; got 'linear'"):
        HiveformerConfig(lr_schedule="linear", device="cpu")
    with pytest.raises(ValueError, match="history_cache_mib must be >= 0, got -1"):
        HiveformerConfig(history_cache_mib=-1, device="cpu")
    with pytest.raises(ValueError, match=r"relabel_probability must be in \[0, 1\], got 1.5"):
        HiveformerConfig(relabel_probability=1.5, device="cpu")


def test_training_decodes_only_supervised_steps_with_the_same_predictions(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [0, 1, 7])  # 2, 1 and 0 padded steps
    supervised = supervised_steps(batch)
    assert supervised.sum() == 4
    obs = keyframe_observations(batch, policy.config)
    instruction, instruction_mask = policy._encode_instructions(obs.instructions, obs.points.device)
    with torch.no_grad():
        window = policy.predict_keyframes(batch)  # every step, padding included: (3, 3, ...)
        decoded = policy.model(obs, instruction, instruction_mask, decode=supervised)  # (4, ...)
    assert decoded.position.shape == (4, 3) and decoded.pixel_attention.shape == (4, 3, 32, 32)
    assert torch.allclose(decoded.position, window.position[supervised], atol=1e-6)
    assert torch.allclose(decoded.quaternion, window.quaternion[supervised], atol=1e-6)
    assert torch.allclose(decoded.pixel_attention, window.pixel_attention[supervised], atol=1e-6)
    # Training builds no pixel maps for the padding steps: the same predictions.
    kept = keyframe_observations(batch, policy.config, keep=supervised)
    assert kept.stem.shape[0] == int(kept.step_valid.sum()) == 6 and obs.stem.shape[0] == 9
    with torch.no_grad():
        from_kept = policy.model(kept, instruction, instruction_mask, decode=supervised)
    assert torch.allclose(from_kept.position, decoded.position, atol=1e-6)
    assert torch.allclose(from_kept.pixel_attention, decoded.pixel_attention, atol=1e-6)


def test_gradients_reach_every_feature_map_channels_last(tiny_dataset_root):
    """The feature maps are channels-last; their gradients must be too (the encoder's skips are selected for
    the supervised steps only), since LeakyReLU's backward pass on mixed layouts is ~8x slower and GroupNorm's
    compiled one takes channels-last gradients (others are copied)."""
    policy = make_tiny_policy(tiny_dataset_root).train()
    batch = history_batch(tiny_dataset_root, policy.config, [0, 1, 7])  # a selection: 4 of 6 real steps
    layouts = {}

    def record_gradient_layout(name):  # on the output tensor: module backward hooks refuse in-place LeakyReLU
        def hook(module, inputs, output):
            output.register_hook(lambda grad: layouts.__setitem__(
                name, grad.is_contiguous(memory_format=torch.channels_last)))
        return hook

    for name, module in policy.model.named_modules():
        if isinstance(module, torch.nn.LeakyReLU | torch.nn.GroupNorm) and "rotation" not in name:
            module.register_forward_hook(record_gradient_layout(name))
    loss, _ = policy.forward(batch)
    loss.backward()
    assert len(layouts) == 2 + 4 + 4  # the stem's two LeakyReLUs, the encoder's and decoder's blocks
    assert all(layouts.values()), [name for name, channels_last in layouts.items() if not channels_last]


def test_only_contexts_a_rollout_produces_are_supervised(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root)  # history 3
    # Episode 3 has 6 keyframes: windows at keyframes 0..5 of it.
    start = EPISODE_STARTS[3]
    batch = history_batch(tiny_dataset_root, config, list(range(start, start + EPISODE_LENGTHS[3])))
    supervised = supervised_steps(batch).tolist()
    assert batch["action"].shape[1] == 4  # the look-back action, then one target per step
    assert supervised == [
        [False, False, True],  # keyframe 0: the window starts at the episode start
        [False, True, True],  # keyframe 1: keyframes 0 and 1 both see their whole history
        # keyframe 2: no padding, yet the window starts at the episode start (the look-back action before it is
        # padding): a rollout's window at keyframe 2 is the same, so every step is supervised. A whole-episode
        # sample of an episode as long as the history is such a window.
        [True, True, True],
        [False, False, True],  # keyframes 3..5: earlier steps of the window see a truncated history
        [False, False, True],
        [False, False, True],
    ]


def test_the_position_offset_starts_at_zero(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root).eval()
    batch = history_batch(tiny_dataset_root, policy.config, [4, 11])
    with torch.no_grad():
        prediction = policy.predict_keyframes(batch)
    obs = keyframe_observations(batch, policy.config)
    attended = torch.einsum("btchw,btckhw->btk", prediction.pixel_attention, obs.points.unflatten(0, (2, -1)))
    assert torch.allclose(prediction.position, attended, atol=1e-6)


def test_rescaling_moves_colour_points_and_mark_together(tiny_dataset_root):
    config, _ = tiny_config(tiny_dataset_root)
    batch = history_batch(tiny_dataset_root, config, [5])
    obs = keyframe_observations(batch, config)
    assert torch.equal(keyframe_observations(batch, config, rescale=(1.0, 1.0)).points, obs.points)
    torch.manual_seed(3)
    for scale in (0.75, 1.25):
        out = keyframe_observations(batch, config, rescale=(scale, scale))
        assert out.stem.shape == obs.stem.shape and out.patch_xyz.shape == obs.patch_xyz.shape
        # Every output pixel is one input pixel: its colour, point and validity travel together.
        before = torch.cat([obs.stem.movedim(-1, 2)[:, :, :3], obs.points, obs.valid_pixels.unsqueeze(2).float()], 2)
        after = torch.cat([out.stem.movedim(-1, 2)[:, :, :3], out.points, out.valid_pixels.unsqueeze(2).float()], 2)
        pairs_before = {tuple(p) for p in before[-1, 0].flatten(1).T.tolist()}
        assert all(tuple(p) in pairs_before for p in after[-1, 0].flatten(1).T.tolist())
        assert torch.equal(out.calibration, obs.calibration)  # calibration is never augmented


@pytest.mark.parametrize("shape", [(6, 32, 32), (2, 3, 7, 5), (1, 1, 1)])
def test_upsample_twice_is_bilinear_interpolation(shape):
    x = torch.randn(*shape, requires_grad=True)
    reference = x.detach().clone().requires_grad_()
    expected = torch.nn.functional.interpolate(reference.reshape(-1, 1, *shape[-2:]), scale_factor=2,
                                               mode="bilinear", align_corners=False)
    got = upsample_twice(x)
    assert got.shape == (*shape[:-2], 2 * shape[-2], 2 * shape[-1])
    assert torch.allclose(got, expected.view(got.shape), atol=1e-6)
    weights = torch.randn(got.shape)
    (got * weights).sum().backward()
    (expected.view(got.shape) * weights).sum().backward()
    assert torch.allclose(x.grad, reference.grad, atol=1e-5)


def test_dropout_zeroes_a_fraction_p_and_scales_the_rest():
    torch.manual_seed(0)
    dropout = Dropout(0.25)
    x = torch.full((200_000,), 2.0, requires_grad=True)
    y = dropout(x)
    assert y.unique().tolist() == [0.0, pytest.approx(2 / 0.75)]
    assert abs(float((y == 0).float().mean()) - 0.25) < 0.005
    y.sum().backward()
    assert torch.equal(x.grad == 0, y == 0)  # the gradient flows through the kept values only
    assert torch.equal(dropout.eval()(x), x)


def test_rescaled_maps_are_the_cameras_resized_padded_and_cropped(tiny_dataset_root):
    """Colour and depth resampled, and the point cloud and mark built from the resampled depth, equal the
    authors' steps done one by one with PyTorch on the camera's maps, random draws included; for windows with
    padding, whose padding steps get no maps, too."""
    config, _ = tiny_config(tiny_dataset_root)
    batch = history_batch(tiny_dataset_root, config, [EPISODE_STARTS[1] + 1, 7, EPISODE_STARTS[2] - 1])
    keep = supervised_steps(batch)
    plain = keyframe_observations(batch, config, keep=keep)
    assert not plain.pixel_steps.all()  # some padding steps are left out
    height, width = plain.points.shape[-2:]
    # the stem's input: colour, point cloud and mark (the 7-channel stem)
    maps = torch.cat([plain.stem.movedim(-1, 2), plain.points, plain.valid_pixels.unsqueeze(2).float()], dim=2)
    sample_of_row = plain.pixel_steps.nonzero()[:, 0]
    for seed, (low, high) in enumerate([(0.75, 1.25), (0.55, 0.8), (1.3, 2.0), (1.0, 1.0)]):
        torch.manual_seed(seed)
        out = keyframe_observations(batch, config, keep=keep, rescale=(low, high))
        got = torch.cat([out.stem.movedim(-1, 2), out.points, out.valid_pixels.unsqueeze(2).float()], dim=2)
        torch.manual_seed(seed)
        for sample in range(keep.shape[0]):
            scale = float(torch.empty(()).uniform_(low, high))
            size = (max(int(height * scale), 1), max(int(width * scale), 1))
            rows = maps[sample_of_row == sample]  # (steps, C, 8, H, W)
            x = torch.nn.functional.interpolate(rows.flatten(0, 1), size=size, mode="nearest")
            x = torch.nn.functional.pad(x, (0, max(width - size[1], 0), 0, max(height - size[0], 0)), mode="reflect")
            top = int(torch.randint(0, x.shape[-2] - height + 1, ()))
            left = int(torch.randint(0, x.shape[-1] - width + 1, ()))
            expected = x[..., top : top + height, left : left + width].unflatten(0, rows.shape[:2])
            assert torch.equal(got[sample_of_row == sample], expected), (seed, sample)
        assert out.stem[..., -1].sum() > 0  # the gripper is seen


@needs_numba
@pytest.mark.parametrize("shape", [(6, 16, 64, 64), (40, 16, 8, 8), (2, 16, 4, 4), (3, 64, 4, 4), (1, 16, 1, 1)])
def test_group_norm_leaky_relu_equals_pytorchs(shape):
    """Same values and gradients (input, weight, bias) as F.group_norm then F.leaky_relu, channels-last in and out
    (the compiled kernels) and NCHW (PyTorch's), with and without autograd."""
    torch.manual_seed(0)
    layer = cpu_kernels.GroupNormLeakyReLU(num_groups=4, num_channels=shape[1], negative_slope=LEAKY_SLOPE)
    with torch.no_grad():
        layer.weight.normal_()
        layer.bias.normal_()
    for memory_format in (torch.channels_last, torch.contiguous_format):
        x = (torch.randn(shape) * 3 + 1).contiguous(memory_format=memory_format).requires_grad_()
        grad = torch.randn(shape).contiguous(memory_format=memory_format)
        out = layer(x)
        normalised = torch.nn.functional.group_norm(x, 4, layer.weight, layer.bias, layer.eps)
        expected = torch.nn.functional.leaky_relu(normalised, LEAKY_SLOPE)
        assert torch.allclose(out, expected, atol=1e-5)
        assert out.is_contiguous(memory_format=memory_format)
        with torch.inference_mode():
            assert torch.allclose(layer(x.detach()), expected, atol=1e-5)
        grads = torch.autograd.grad(out, (x, layer.weight, layer.bias), grad)
        expected_grads = torch.autograd.grad(expected, (x, layer.weight, layer.bias), grad)
        for got, want in zip(grads, expected_grads, strict=True):
            assert torch.allclose(got, want, rtol=1e-4, atol=1e-4 * float(want.abs().max()))
        assert grads[0].is_contiguous(memory_format=memory_format)
    assert (out < 0).any() and (out > 0).any()  # both sides of the activation were exercised


@needs_numba
def test_group_norm_leaky_relu_is_accurate_where_the_mean_dwarfs_the_spread():
    """A map whose mean is 100 times its spread: float32 sums of E[x²] - E[x]² lose the variance there (a training
    run's loss jumped with them); the kernels' float64 sums keep the output within PyTorch's own float32 error."""
    torch.manual_seed(0)
    x = torch.randn(8, 16, 32, 32, dtype=torch.float64) * 0.1 + 10
    layer = cpu_kernels.GroupNormLeakyReLU(num_groups=4, num_channels=16, negative_slope=LEAKY_SLOPE)
    exact = torch.nn.functional.leaky_relu(torch.nn.functional.group_norm(x, 4, layer.weight.double(),
                                                                          layer.bias.double(), layer.eps), LEAKY_SLOPE)
    with torch.no_grad():
        got = layer(x.float().contiguous(memory_format=torch.channels_last))
    assert float((got.double() - exact).abs().max()) < 1e-4


@needs_numba
@pytest.mark.parametrize("stem_point_cloud", [True, False])
def test_the_compiled_maps_are_pytorchs_bit_for_bit(tiny_dataset_root, stem_point_cloud):
    """`keyframe_maps` (one compiled pass) gives PyTorch's stem input, point cloud, validity and patch points bit for
    bit, augmented or not, for windows whose padding steps get no maps: a training run takes the same path."""
    config, _ = tiny_config(tiny_dataset_root, stem_point_cloud=stem_point_cloud)
    batch = history_batch(tiny_dataset_root, config, [EPISODE_STARTS[1] + 1, 7, EPISODE_STARTS[2] - 1])
    keep = supervised_steps(batch)
    for rescale in (None, (0.75, 1.25), (1.3, 2.0)):
        torch.manual_seed(0)
        compiled = keyframe_observations(batch, config, keep=keep, rescale=rescale,
                                         build_maps=cpu_kernels.keyframe_maps)
        torch.manual_seed(0)
        eager = keyframe_observations(batch, config, keep=keep, rescale=rescale)  # PyTorch's operations
        assert not compiled.pixel_steps.all()  # padding steps left out
        assert compiled.stem.shape == (int(compiled.pixel_steps.sum()), 3, 32, 32, 7 if stem_point_cloud else 4)
        assert compiled.patch_xyz.shape == (int(compiled.pixel_steps.sum()), 3, 3, 2, 2)
        for name in ("stem", "points", "valid_pixels", "patch_xyz"):
            got, want = getattr(compiled, name), getattr(eager, name)
            assert got.dtype == want.dtype and got.shape == want.shape
            assert torch.equal(got.view(torch.int32) if got.is_floating_point() else got,
                               want.view(torch.int32) if want.is_floating_point() else want), (rescale, name)


@needs_numba
@pytest.mark.parametrize("shape", [(40, 16, 16, 16), (3, 16, 4, 4), (2, 32, 3, 7), (1, 16, 1, 1), (2, 5, 3, 7)])
def test_bilinear_upsample_is_pytorchs_bit_for_bit(shape):
    """The compiled 2x bilinear upsampling of channels-last maps gives F.interpolate's values and gradients bit for
    bit; other sizes and channel counts take F.interpolate itself."""
    torch.manual_seed(0)
    x = torch.randn(shape).contiguous(memory_format=torch.channels_last).requires_grad_()
    reference = x.detach().clone().contiguous(memory_format=torch.channels_last).requires_grad_()
    size = (2 * shape[2], 2 * shape[3])
    got = cpu_kernels.bilinear_upsample(x, size)
    expected = torch.nn.functional.interpolate(reference, size=size, mode="bilinear", align_corners=False)
    assert torch.equal(got, expected) and got.is_contiguous(memory_format=torch.channels_last)
    for grad in (torch.randn_like(expected), torch.randn(expected.shape)):  # channels-last, then NCHW
        (g,) = torch.autograd.grad(got, x, grad, retain_graph=True)
        (want,) = torch.autograd.grad(expected, reference, grad, retain_graph=True)
        assert torch.equal(g, want)
    odd = cpu_kernels.bilinear_upsample(x, (shape[2] + 1, shape[3]))  # not doubled: PyTorch's
    assert torch.equal(odd, torch.nn.functional.interpolate(reference, size=(shape[2] + 1, shape[3]), mode="bilinear",
                                                            align_corners=False))


@needs_numba
@pytest.mark.parametrize("shape", [(6, 3, 3, 64 * 64), (2, 1, 3, 5), (1, 3, 3, 1)])
def test_weighted_points_gradient_is_the_batched_products(shape):
    """The compiled gradient of the attended point's weights is the batched product's within float32 rounding: bit
    for bit where MKL's product adds its 3 terms in the loop's order (an AMD EPYC with AVX-512), up to ~5e-7 apart
    on a third of the values (of magnitude up to ~6) where it orders them otherwise (an Intel Xeon with AMX)."""
    torch.manual_seed(0)
    points = torch.randn(shape) * 0.5
    weights = torch.rand(*shape[:-2], shape[-1], 1).softmax(-2).requires_grad_()
    reference = weights.detach().clone().requires_grad_()
    got, expected = cpu_kernels.weighted_points(points, weights), points @ reference
    assert torch.equal(got, expected)
    grad = torch.randn_like(got)
    got.backward(grad)
    expected.backward(grad)
    torch.testing.assert_close(weights.grad, reference.grad, rtol=1e-6, atol=1e-6)


def test_conv_block_of_concatenation_equals_the_block_on_the_concatenation():
    torch.manual_seed(0)
    block = ConvBlock(24, 16)
    parts = [torch.randn(5, 8, 16, 16).contiguous(memory_format=torch.channels_last).requires_grad_(),
             torch.randn(5, 16, 16, 16).contiguous(memory_format=torch.channels_last).requires_grad_()]
    out = conv_block_of_concatenation(block, parts)
    expected = block(torch.cat(parts, dim=1))
    assert torch.allclose(out, expected, atol=1e-5) and out.is_contiguous(memory_format=torch.channels_last)
    grad = torch.randn_like(out)
    wrt = [*parts, *block.parameters()]
    for got, want in zip(torch.autograd.grad(out, wrt, grad), torch.autograd.grad(expected, wrt, grad), strict=True):
        assert torch.allclose(got, want, atol=1e-4)


def test_optimiser_preset_is_the_authors(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root)
    preset = policy.config.get_optimizer_preset()
    assert (preset.lr, preset.weight_decay, preset.grad_clip_norm) == (1e-3, 5e-4, 0.0)
    optimizer = preset.build(policy.get_optim_params())  # PyTorch's fused AdamW: one kernel, not a loop over tensors
    assert isinstance(optimizer, torch.optim.AdamW) and optimizer.defaults["fused"] is True
    assert preset.type == "adamw_fused"
    decayed, plain = policy.get_optim_params()
    assert plain["weight_decay"] == 0.0 and "weight_decay" not in decayed
    norms = (torch.nn.LayerNorm, torch.nn.GroupNorm)
    norm_weights = {id(m.weight) for m in policy.modules() if isinstance(m, norms)}
    biases = {id(p) for name, p in policy.named_parameters() if name.endswith("bias")}
    assert {id(p) for p in plain["params"]} == norm_weights | biases
    assert len(plain["params"]) + len(decayed["params"]) == len(list(policy.parameters()))


def learning_rates(policy, config: HiveformerConfig, steps: int) -> list[float]:
    """The rate at each of `steps` optimiser steps, with the optimiser and scheduler built as lerobot-train does."""
    optimizer = config.get_optimizer_preset().build(policy.get_optim_params())
    scheduler = config.get_scheduler_preset().build(optimizer, num_training_steps=steps)
    rates = []
    for _ in range(steps):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return rates


def test_cosine_schedule_anneals_the_authors_rate_to_zero_over_the_run(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root)
    assert policy.config.get_scheduler_preset() is None  # the authors': constant
    rates = learning_rates(policy, HiveformerConfig(lr_schedule="cosine", device="cpu"), steps=100)
    assert rates[0] == pytest.approx(1e-3) and rates[50] == pytest.approx(5e-4)
    assert all(a > b for a, b in zip(rates, rates[1:])) and rates[-1] < 1e-6


def test_warmup_ramps_the_rate_up_before_the_cosine_anneals_it(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root)
    config = HiveformerConfig(lr_schedule="cosine", lr_warmup_steps=10, device="cpu")
    rates = learning_rates(policy, config, steps=110)
    assert rates[0] == 0 and rates[5] == pytest.approx(5e-4) and rates[10] == pytest.approx(1e-3)
    assert rates[60] == pytest.approx(5e-4) and rates[-1] < 1e-6
    with pytest.raises(ValueError, match="lr_warmup_steps must be >= 0, and 0 unless lr_schedule='cosine'; got 10 "
                                         "with lr_schedule='constant'"):
        HiveformerConfig(lr_warmup_steps=10, device="cpu")


def test_constant_then_cosine_holds_the_rate_then_anneals_it_over_the_last_steps(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root)
    config = HiveformerConfig(lr_schedule="constant_then_cosine", lr_decay_fraction=0.25, device="cpu")
    assert config.get_scheduler_preset().type == "constant_then_cosine"
    rates = learning_rates(policy, config, steps=200)
    assert rates[:151] == [pytest.approx(1e-3)] * 151  # held for the first 150 steps (and the decay's step 0)
    assert rates[175] == pytest.approx(5e-4) and rates[-1] < 1e-6  # half-way through the last 50: half the rate
    assert all(a > b for a, b in zip(rates[150:], rates[151:]))
    with pytest.raises(ValueError, match=r"lr_decay_fraction must be in \(0, 1\], got 0"):
        HiveformerConfig(lr_schedule="constant_then_cosine", lr_decay_fraction=0, device="cpu")


def test_minilm_is_a_real_pretrained_encoder_that_needs_no_download(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root, text_encoder="minilm")
    encoder = policy.instruction_encoder
    features, mask = encoder.encode(["press the navy button, then the teal one", "open the top drawer"])
    assert features.shape[-1] == 384 and mask.sum(1).tolist()[1] == 6  # [CLS] open the top drawer [SEP]
    pooled = [(f[m]).mean(0) for f, m in zip(features, mask)]
    swapped, _ = encoder.encode(["press the teal button, then the navy one"])
    # Pretrained: paraphrases of one task are closer to each other than to another task.
    similar = torch.cosine_similarity(pooled[0], swapped[0].mean(0), dim=0)
    different = torch.cosine_similarity(pooled[0], pooled[1], dim=0)
    assert similar > 0.9 > 0.6 > different
    batch = history_batch(tiny_dataset_root, policy.config, [2])
    loss, _ = policy.forward(batch)
    assert math.isfinite(loss.item())


def test_loading_minilm_prints_nothing_alarming_and_a_real_mismatch_is_raised(tmp_path):
    import shutil
    import subprocess
    import sys

    from safetensors.torch import load_file, save_file

    from lerobot_policy_hiveformer.text_encoders import _load_text_model, minilm_model_dir

    # In a process of its own, as a user loads it (transformers' log handler writes to the stderr it first saw):
    # its checkpoint holds position ids that BERT now builds itself, and no load report, UNEXPECTED key, progress
    # bar or sharding warning is printed.
    load = ("from lerobot_policy_hiveformer.text_encoders import _load_text_model, minilm_model_dir; "
            "print(_load_text_model(minilm_model_dir()).config.hidden_size)")
    printed = subprocess.run([sys.executable, "-c", load], capture_output=True, text=True)
    assert (printed.returncode, printed.stdout, printed.stderr) == (0, "384\n", ""), printed
    broken = tmp_path / "minilm"
    shutil.copytree(minilm_model_dir(), broken)
    weights = load_file(broken / "model.safetensors")
    save_file({k: v for k, v in weights.items() if "pooler" not in k}, broken / "model.safetensors")
    with pytest.raises(ValueError, match="missing: .*pooler"):
        _load_text_model(broken)


def test_minilm_words_gives_a_word_the_same_features_wherever_it_stands(tiny_dataset_root):
    policy = make_tiny_policy(tiny_dataset_root, text_encoder="minilm_words")
    features, mask = policy.instruction_encoder.encode(["press the navy button, then the blue one",
                                                       "press the blue button, then the navy one"])
    assert features.shape[-1] == 384 and mask.all()
    # [CLS] press the navy button , then the blue one [SEP]: navy at 3 and 8, blue at 8 and 3.
    assert torch.equal(features[0, 3], features[1, 8]) and torch.equal(features[0, 8], features[1, 3])
    assert not torch.equal(features[0, 3], features[0, 8])
    contextual, _ = make_tiny_policy(tiny_dataset_root, text_encoder="minilm").instruction_encoder.encode(
        ["press the navy button, then the teal one", "press the blue button, then the navy one"])
    assert not torch.allclose(contextual[0, 3], contextual[1, 8])  # the contextual features differ by place
    causal, _ = make_tiny_policy(tiny_dataset_root, text_encoder="minilm_causal").instruction_encoder.encode(
        ["press the navy button, then the teal one", "press the navy button, then the blue one"])
    # Left context only: the first 8 tokens are the same sentence start, whatever follows; the next one differs.
    assert torch.allclose(causal[0, :8], causal[1, :8], atol=1e-5) and not torch.allclose(causal[0, 8], causal[1, 8])
    assert not torch.allclose(causal[0, 3], contextual[0, 3])  # ... where the whole sentence changes every token
    loss, _ = policy.forward(history_batch(tiny_dataset_root, policy.config, [2]))
    assert math.isfinite(loss.item())


def test_colour_features_give_a_colour_name_its_colour_whatever_the_word(tiny_dataset_root):
    from lerobot_policy_hiveformer.colour_names import colour_spans

    text = "Press the dark blue button, then the scarlet one, then blue-green; then wine, not winery"
    assert [text[a:b] for a, b, _ in colour_spans(text)] == ["dark blue", "scarlet", "blue-green", "wine"]
    policy = make_tiny_policy(tiny_dataset_root, text_encoder="minilm_words", colour_features=True)
    features, mask = policy.instruction_encoder.encode(["press the red button", "press the scarlet button",
                                                       "press the navy button", "press the dark blue button"])
    assert features.shape[-1] == 384 + 4 and mask.sum(1).tolist() == [6, 6, 6, 7]  # dark blue: two tokens
    # [CLS] press the red button [SEP]: the colour word holds its coordinates and a 1 beside its text features.
    red, scarlet, navy, dark_blue = features[0, 3], features[1, 3], features[2, 3], features[3, 3:5]
    assert red[-1] == 1 and red[:384].any() and not features[0, 2, 384:].any() and features[0, 2, :384].any()
    plain, _ = make_tiny_policy(tiny_dataset_root, text_encoder="minilm_words").instruction_encoder.encode(
        ["press the red button"])
    assert torch.equal(red[:384], plain[0, 3])  # the word's own features, unchanged
    assert torch.equal(dark_blue[0, -4:], dark_blue[1, -4:])  # every token of the name
    # A synonym no palette holds is nearer its colour than another: what one-hot or word-piece codes cannot say.
    assert torch.dist(scarlet[-4:-1], red[-4:-1]) < torch.dist(scarlet[-4:-1], navy[-4:-1])
    assert torch.dist(dark_blue[0, -4:-1], navy[-4:-1]) < torch.dist(dark_blue[0, -4:-1], red[-4:-1])
    assert math.isfinite(policy.forward(history_batch(tiny_dataset_root, policy.config, [2]))[0].item())
    with pytest.raises(ValueError, match="colour_features needs a minilm text_encoder .*; got 'one_hot'"):
        HiveformerConfig(text_encoder="one_hot", colour_features=True, device="cpu")


def test_colour_word_dropout_zeroes_only_colour_words_text_and_only_in_training(tiny_dataset_root):
    from lerobot_policy_hiveformer.modeling_hiveformer import drop_colour_words

    policy = make_tiny_policy(tiny_dataset_root, text_encoder="minilm_words", colour_features=True,
                              colour_word_dropout=1.0)
    features, _ = policy.instruction_encoder.encode(["press the red button, then the navy one"])
    dropped = drop_colour_words(features, 1.0)
    colour = features[0, :, -1] > 0
    assert colour.sum() == 2 and not dropped[0, colour, :384].any()
    assert torch.equal(dropped[0, colour, 384:], features[0, colour, 384:])  # the coordinates stay
    assert torch.equal(dropped[0, ~colour], features[0, ~colour])  # every other token unchanged
    assert torch.equal(drop_colour_words(features, 0.0), features)
    policy.eval()
    kept, _ = policy._encode_instructions(["press the red button, then the navy one"], torch.device("cpu"))
    assert torch.equal(kept, features)
    policy.train()
    trained, _ = policy._encode_instructions(["press the red button, then the navy one"], torch.device("cpu"))
    assert torch.equal(trained, dropped)
    assert math.isfinite(policy.forward(history_batch(tiny_dataset_root, policy.config, [2]))[0].item())
    for wrong in ({"colour_word_dropout": 1.5, "colour_features": True}, {"colour_word_dropout": 0.5}):
        with pytest.raises(ValueError, match="colour_word_dropout must be in"):
            HiveformerConfig(text_encoder="minilm_words", device="cpu", **wrong)


def test_measure_compute_times_each_part_of_every_rollout_step(tiny_dataset_root):
    """The benchmark's split of a rollout step (measure_compute.py) times each part once per step."""
    from lerobot_policy_hiveformer import measure_compute as measure

    policy = make_tiny_policy(tiny_dataset_root)
    config, _ = tiny_config(tiny_dataset_root)
    batch = history_batch(tiny_dataset_root, config, [0, 1, 2])
    steps = measure.timed_parts(policy)
    policy.reset()
    for step in range(3):
        policy.select_action(single_step(batch, step))
    assert len(steps) == 3
    for parts in steps:
        assert set(parts) == {"encoder", "transformer", "attention", "heads", "decoder"}
        assert 0 < parts["attention"] < parts["transformer"] and 0 < parts["decoder"] < parts["heads"]
    attention, conv2d = torch.nn.functional.scaled_dot_product_attention, torch.nn.functional.conv2d
    observation = single_step(batch, 2)
    alone = measure.kernels_alone_ms(policy, lambda: policy.select_action(observation), repeats=3)
    assert set(alone) == {"convolutions", "attention"} and all(ms > 0 for ms in alone.values())
    assert torch.nn.functional.scaled_dot_product_attention is attention  # put back
    assert torch.nn.functional.conv2d is conv2d
    assert not any(module._forward_hooks for module in policy.modules())
    # A training step's floor: the same kernels with their backward passes, each alone.
    policy.train()
    training = measure.kernels_alone_ms(policy, lambda: policy.forward(batch), repeats=3, backward=True)
    assert set(training) == {"convolutions", "attention"} and all(ms > 0 for ms in training.values())
    assert not any(module._forward_hooks for module in policy.modules())
    assert all(p.grad is None for p in policy.parameters())  # measuring trains nothing


FAULTS_OF_REPEATED_BIG_TENSORS = """
import resource, torch

def faults() -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        torch.ones(64 * 2**20 // 4)  # 64 MiB, freed at once
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

for _ in range(3):  # the heap grows to hold the five tensors over the first rounds (one or two, by what the imports
    faults()        # left in it), then serves every round from memory it keeps, if malloc keeps it
print(faults())
"""


@pytest.mark.skipif(not (sys.platform == "linux" and platform.libc_ver()[0] == "glibc"), reason="glibc only")
def test_the_launchers_malloc_settings_keep_freed_memory():
    """Glibc's default maps every big tensor afresh (16,384 page faults per 64 MiB); in the environment the reference
    runs give lerobot-train (and `make bench`, the same values), a freed tensor's memory serves the next one."""
    from demo_factory.tools.reference_run import KEEP_FREED_MEMORY

    def faults(env: dict) -> int:
        result = subprocess.run([sys.executable, "-c", FAULTS_OF_REPEATED_BIG_TENSORS], capture_output=True, text=True,
                                check=True, env=env)
        return int(result.stdout)

    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    assert faults(clean) >= 5 * 16_000 and faults({**clean, **KEEP_FREED_MEMORY}) < 1_000
    makefile = (Path(__file__).parents[1] / "Makefile").read_text()
    assert f"KEEP_FREED_MEMORY := {' '.join(f'{k}={v}' for k, v in KEEP_FREED_MEMORY.items())}\n" in makefile


def test_a_configuration_saved_with_the_old_malloc_field_loads_and_changes_nothing(tiny_dataset_root, tmp_path):
    """A config.json saved with `retain_freed_memory` (when the policy set glibc's malloc options) still loads; the
    field is ignored (the launcher's environment sets those options now)."""
    from lerobot.configs.policies import PreTrainedConfig

    config, _ = tiny_config(tiny_dataset_root, hidden_dim=48)
    config._save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    (tmp_path / "config.json").write_text(json.dumps({**saved, "retain_freed_memory": True}))
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(loaded, HiveformerConfig) and loaded.hidden_dim == 48 and loaded.retain_freed_memory is True


NOTHING_OUTSIDE_THE_POLICY = """
import os, sys
sys.path.insert(0, sys.argv[1])
import torch, transformers.models.clip, open_clip.tokenizer  # the plugin's dependencies, which set what they set
import lerobot.datasets.lerobot_dataset, lerobot.policies.pretrained, lerobot.processor
from hiveformer_fixtures import history_batch, tiny_config
threads, environment = torch.get_num_threads(), dict(os.environ)
from lerobot_policy_hiveformer import HiveformerPolicy
config, meta = tiny_config(sys.argv[2])
policy = HiveformerPolicy(config, dataset_meta=meta)
loss, _ = policy.forward(history_batch(sys.argv[2], config, [2, 8]))
loss.backward()
assert "numba" not in sys.modules, "numba imported"
assert torch.get_num_threads() == threads and dict(os.environ) == environment
""" + FAULTS_OF_REPEATED_BIG_TENSORS


@pytest.mark.skipif(not (sys.platform == "linux" and platform.libc_ver()[0] == "glibc"), reason="glibc only")
def test_importing_and_training_the_policy_changes_nothing_in_the_process(tiny_dataset_root):
    """Importing the plugin, building a policy and taking a training step (PyTorch's operations, the default) import no
    numba and leave torch's threads, the environment and glibc's malloc (every big tensor still faulted in afresh)
    as they were. In its own process, since those settings are the process's."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    result = subprocess.run([sys.executable, "-c", NOTHING_OUTSIDE_THE_POLICY, str(Path(__file__).parent),
                             str(tiny_dataset_root)], capture_output=True, text=True, env=clean)
    assert result.returncode == 0, result.stderr[-2000:]
    assert int(result.stdout.split()[-1]) >= 5 * 16_000


@needs_numba
def test_the_cpu_kernels_switch_gives_pytorchs_losses_and_gradients(tiny_dataset_root):
    """`cpu_kernels=true` builds the compiled layers and trains on the same values as PyTorch's operations (GroupNorm's
    within float32 rounding), from the same initial parameters."""
    settings = {"augmentation_min_scale": 1.0, "augmentation_max_scale": 1.0, "attention_dropout": 0.0}
    plain = make_tiny_policy(tiny_dataset_root, **settings)
    compiled = make_tiny_policy(tiny_dataset_root, **settings, cpu_kernels=True)
    compiled.load_state_dict(plain.state_dict())
    assert any(isinstance(m, cpu_kernels.GroupNormLeakyReLU) for m in compiled.modules())
    assert not any(isinstance(m, cpu_kernels.GroupNormLeakyReLU) for m in plain.modules())
    batch = history_batch(tiny_dataset_root, plain.config, [2, 8, 13])
    losses = []
    for policy in (plain, compiled):
        policy.train()
        loss, _ = policy.forward(batch)
        loss.backward()
        losses.append(loss.detach())
    torch.testing.assert_close(losses[0], losses[1], rtol=1e-5, atol=1e-6)
    for (name, p), q in zip(plain.named_parameters(), compiled.parameters(), strict=True):
        if p.grad is not None:
            torch.testing.assert_close(p.grad, q.grad, rtol=1e-3, atol=1e-5, msg=name)
