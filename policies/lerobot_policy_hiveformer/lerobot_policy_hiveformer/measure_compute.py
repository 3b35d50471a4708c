"""Measure HiveFormer's size and CPU speed at the paper's settings (3 cameras 128x128, history 6).

    python -m lerobot_policy_hiveformer.measure_compute [--batch-size 8] [--threads 2] [--inference-threads 1]
        [--cpu-kernels]

Times are medians over steps. `inference_ms_by_part` splits a rollout step into the encoder's and the
decoder's convolutions, the attention calls, the whole transformer and the heads (decoder included).
`inference_kernels_alone_ms` re-runs each convolution and attention call of one rollout step alone, on
its own inputs (caches hot): the time those calls need with nothing else, below which a step cannot go.
`*_cpu_*` is the process's CPU time for the same steps (user + system, all threads), which tells a slow
step on a busy machine (wall > CPU / threads) from a slow step. The load average is the machine's at
the start. Peak RSS is the whole process's (the frozen text encoder
included) after the training steps.

The frozen text encoder has CLIP ViT-B/32's text architecture with random weights (saved to a temporary
directory and loaded through `text_encoder_path`, the offline route), so no download is needed; the
parameter counts are those of the real model.
"""

import argparse
import functools
import json
import os
import resource
import tempfile
import time

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.configs.types import FeatureType, PolicyFeature
from transformers import CLIPTextConfig, CLIPTextModel

from lerobot_policy_hiveformer import HiveformerConfig, HiveformerPolicy

CAMERAS = ("left_shoulder", "right_shoulder", "wrist")


def features(size: int) -> tuple[dict, dict]:
    inputs = {}
    for camera in CAMERAS:
        inputs[f"observation.images.{camera}"] = PolicyFeature(FeatureType.VISUAL, (3, size, size))
        inputs[f"observation.depth.{camera}"] = PolicyFeature(FeatureType.VISUAL, (1, size, size))
        inputs[f"observation.calibration.{camera}"] = PolicyFeature(FeatureType.STATE, (20,))
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (15,))
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (8,))}


def calibration(camera_index: int, size: int) -> torch.Tensor:
    """A camera 0.6-0.8 m above the table looking down (OpenCV axes)."""
    focal = 1.1 * size
    world_from_camera = np.diag([1.0, -1.0, -1.0, 1.0])
    world_from_camera[:3, 3] = [0.1 * camera_index, 0.0, 0.6 + 0.1 * camera_index]
    return torch.tensor([focal, focal, (size - 1) / 2, (size - 1) / 2, *world_from_camera.reshape(-1)])


def observation_batch(batch_size: int, steps: int | None, size: int) -> dict:
    """Random RGB, a flat table 0.6-0.8 m away (depth in mm), real-looking calibration and state."""
    lead = (batch_size,) if steps is None else (batch_size, steps)
    batch = {}
    for i, camera in enumerate(CAMERAS):
        batch[f"observation.images.{camera}"] = torch.rand(*lead, 3, size, size)
        batch[f"observation.depth.{camera}"] = torch.full((*lead, 1, size, size), 600.0 + 100 * i)
        batch[f"observation.calibration.{camera}"] = calibration(i, size).float().expand(*lead, 20).clone()
    state = torch.zeros(*lead, 15)
    state[..., :3] = torch.rand(*lead, 3) * 0.2
    state[..., 6] = 1.0
    batch["observation.state"] = state
    batch["task"] = ["push the maroon button"] * batch_size
    if steps is not None:
        batch["observation.state_is_pad"] = torch.zeros(batch_size, steps, dtype=torch.bool)
        action = torch.zeros(batch_size, steps, 8)
        action[..., 6] = 1.0
        batch["action"] = action
        batch["action_is_pad"] = torch.zeros(batch_size, steps, dtype=torch.bool)
    return batch


def timed_parts(policy) -> list[dict[str, float]]:
    """From now on, each rollout step's seconds in its parts: one {part: seconds} per `select_action`.

    "encoder" and "decoder" are the UNet's convolutions (with their GroupNorm and LeakyReLU),
    "attention" the transformer's attention calls, "transformer" the whole of it (attention
    included) and "heads" the decoder plus the rotation/gripper head.
    """
    steps: list[dict[str, float]] = []

    def timed(name, function):
        def call(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                steps[-1][name] = steps[-1].get(name, 0.0) + time.perf_counter() - start

        return call

    select_action = policy.select_action
    policy.select_action = lambda batch: steps.append({}) or select_action(batch)
    model = policy.model
    parts = [("encoder", model.encoder, "forward"), ("transformer", model, "contextualise"),
             ("heads", model, "decode_steps"), ("decoder", model.decoder, "forward")]
    parts += [("attention", attention, "_attend") for layer in model.layers  # every path's attention call
              for attention in (layer.cross_attention, layer.self_attention)]
    for name, owner, method in parts:
        setattr(owner, method, timed(name, getattr(owner, method)))
    return steps


def kernels_alone_ms(policy, step, repeats: int = 50, backward: bool = False) -> dict[str, float]:
    """Milliseconds of the convolutions and attention calls of `policy` that `step()` makes, each re-run alone (median
    of `repeats`) on the inputs it had: the time those kernels need with nothing else, below which the step
    cannot go. With `backward`, each call is timed with its backward pass too (the gradients of its inputs
    that needed them and of its weights), as in a training step.
    """
    return kernel_calls_ms(record_kernel_calls(step), repeats, backward)


def record_kernel_calls(step) -> list[tuple]:
    """The convolution and attention calls `step()` makes, with their inputs: (kind, function, args, kwargs)."""
    calls = []
    # Recorded where every convolution goes through, `nn.Conv2d` and the policy's direct calls alike.
    kernels = {"conv2d": "convolutions", "scaled_dot_product_attention": "attention"}
    originals = {name: getattr(F, name) for name in kernels}

    def recorder(name):
        def recorded(*args, **kwargs):
            calls.append((kernels[name], originals[name], args, kwargs))
            return originals[name](*args, **kwargs)

        return recorded

    for name in kernels:
        setattr(F, name, recorder(name))
    try:
        step()
    finally:
        for name, function in originals.items():
            setattr(F, name, function)
    return calls


def kernel_calls_ms(calls: list[tuple], repeats: int, backward: bool = False) -> dict[str, float]:
    """Milliseconds of each kind of recorded call (`record_kernel_calls`), each call re-run `repeats` times in a
    row (caches hot) and its median kept; with `backward`, each with its backward pass."""
    totals = {"convolutions": 0.0, "attention": 0.0}
    for kind, function, args, kwargs in calls:
        call = _backward_call(function, args, kwargs) if backward else _inference_call(function, args, kwargs)
        durations = []
        for _ in range(repeats):
            start = time.perf_counter()
            call()
            durations.append(time.perf_counter() - start)
        totals[kind] += 1000 * float(np.median(durations))
    return {kind: round(ms, 2) for kind, ms in totals.items()}


def _inference_call(function, args, kwargs):
    def call():
        with torch.inference_mode():
            function(*args, **kwargs)

    return call


def _backward_call(function, args, kwargs):
    """Forward and backward of one recorded call, on detached copies of its inputs that need the same grads."""
    args = [a.detach().requires_grad_(a.requires_grad) if isinstance(a, torch.Tensor) else a for a in args]
    wrt = [a for a in args if isinstance(a, torch.Tensor) and a.requires_grad]
    if isinstance(function, torch.nn.Module):
        wrt += [p for p in function.parameters() if p.requires_grad]

    def call():
        output = function(*args, **kwargs)
        torch.autograd.grad(output, wrt, torch.ones_like(output))

    return call


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--threads", type=int, default=2, help="torch threads for the training steps")
    parser.add_argument("--inference-threads", type=int, default=1, help="torch threads for the rollout steps")
    parser.add_argument("--train-steps", type=int, default=5)
    parser.add_argument("--rollout-steps", type=int, default=60)
    parser.add_argument(
        "--attention-dropout",
        type=float,
        default=None,
        help="override the config's attention_dropout (default 0.1, as in the authors' code)",
    )
    parser.add_argument("--cpu-kernels", action="store_true", help="the compiled CPU loops (config `cpu_kernels`)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load_average = os.getloadavg()

    with tempfile.TemporaryDirectory() as clip_dir:
        CLIPTextModel(CLIPTextConfig()).save_pretrained(clip_dir)  # ViT-B/32 text architecture
        inputs, outputs = features(args.image_size)
        config = HiveformerConfig(
            device="cpu",
            text_encoder="clip",
            text_encoder_path=clip_dir,
            n_history=6,
            cpu_kernels=args.cpu_kernels,
            input_features=inputs,
            output_features=outputs,
        )
        if args.attention_dropout is not None:
            config.attention_dropout = args.attention_dropout
        policy = HiveformerPolicy(config)
    trainable = sum(p.numel() for p in policy.parameters() if p.requires_grad)
    frozen = sum(p.numel() for p in policy.instruction_encoder.text_model.parameters())

    optimizer = config.get_optimizer_preset().build(policy.get_optim_params())  # as lerobot-train builds it
    batch = observation_batch(args.batch_size, config.n_history, args.image_size)
    policy.train()
    durations, cpu_times = [], []
    for _ in range(args.train_steps + 1):
        start, cpu_start = time.perf_counter(), time.process_time()
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        durations.append(time.perf_counter() - start)
        cpu_times.append(time.process_time() - cpu_start)
    # The first step also encodes the instruction.
    train_step_s, train_step_cpu_s = float(np.median(durations[1:])), float(np.median(cpu_times[1:]))
    peak_rss_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # Linux: KiB

    torch.set_num_threads(args.inference_threads)
    policy.reset()
    durations = []
    steps = timed_parts(policy)
    for _ in range(args.rollout_steps):
        observation = observation_batch(1, None, args.image_size)
        start = time.perf_counter()
        policy.select_action(observation)
        durations.append(time.perf_counter() - start)
    inference_ms = 1000 * float(np.median(durations[config.n_history :]))
    part_ms = {name: round(1000 * float(np.median([step.get(name, 0.0) for step in steps[config.n_history :]])), 2)
               for name in ("encoder", "transformer", "attention", "heads", "decoder")}
    rollout_observation = observation_batch(1, None, args.image_size)
    kernels_ms = kernels_alone_ms(policy, lambda: policy.select_action(rollout_observation))

    print(
        json.dumps(
            {
                "trainable_parameters": trainable,
                "frozen_text_encoder_parameters": frozen,
                "train_step_s": round(train_step_s, 3),
                "train_step_cpu_s": round(train_step_cpu_s, 3),
                "train_batch_size": args.batch_size,
                "attention_dropout": config.attention_dropout,
                "peak_rss_gib_after_training": round(peak_rss_gib, 2),
                "inference_ms_per_step_with_full_history": round(inference_ms, 1),
                "inference_ms_by_part": part_ms,
                "inference_kernels_alone_ms": kernels_ms,
                "n_history": config.n_history,
                "image_size": args.image_size,
                "threads": args.threads,
                "inference_threads": args.inference_threads,
                "load_average_1_5_15_min_at_start": [round(x, 2) for x in load_average],
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
