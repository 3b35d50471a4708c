"""Three CPU training steps of HiveFormer in each recipe `demo_factory/tools/reference_run.py` trains, on the tiny
dataset of `hiveformer_fixtures`, from a fixed seed: the parameters they leave tell whether a change to the plugin
changed what a training computes.

    python tests/hiveformer_recipe_steps.py save BASELINE.pt [--policy.FIELD=VALUE ...]
    python tests/hiveformer_recipe_steps.py compare BASELINE.pt [--policy.FIELD=VALUE ...]

`compare` prints, per recipe, whether every parameter is equal bit for bit, else the largest difference.
"""

import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from hiveformer_fixtures import history_batch, tiny_config, write_tiny_dataset  # noqa: E402

from demo_factory.tools.reference_run import SEEN_RECIPE, TOWER_RECIPE, UNSEEN_RECIPE, UNSEEN  # noqa: E402

# Each recipe with the text encoder its reference run uses (one-hot, except make reference-unseen's).
RECIPES = {
    "seen": SEEN_RECIPE | {"text_encoder": "one_hot"},
    "unseen": UNSEEN_RECIPE | {"text_encoder": UNSEEN["text_encoder"]},
    "tower": TOWER_RECIPE | {"text_encoder": "one_hot"},
}
STEPS = 3
SEED = 1000
BATCH_INDICES = ([0, 3, 5, 9, 12, 17], [1, 4, 6, 10, 13, 18], [2, 7, 8, 11, 14, 16])


def recipe_parameters(root: Path, recipe: dict, **overrides) -> dict[str, torch.Tensor]:
    """The parameters after STEPS training steps (the recipe's optimiser and schedule, attention dropout 0 as the
    reference runs train on CPU, dropout 0.1, the rescale augmentation on) from seed SEED."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot_policy_hiveformer import HiveformerPolicy

    torch.manual_seed(SEED)
    config, _ = tiny_config(root, **{"dropout": 0.1, "attention_dropout": 0.0, **recipe, **overrides})
    meta = LeRobotDatasetMetadata("local/tiny", root=root)
    policy = HiveformerPolicy(config, dataset_meta=meta)
    policy.train()
    optimizer = config.get_optimizer_preset().build(policy.get_optim_params())
    scheduler_config = config.get_scheduler_preset()
    scheduler = scheduler_config.build(optimizer, STEPS) if scheduler_config is not None else None
    batches = [history_batch(root, config, indices) for indices in BATCH_INDICES]
    torch.manual_seed(SEED)
    for batch in batches:
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
    return {name: p.detach().clone() for name, p in policy.named_parameters()}


def all_recipes(**overrides) -> dict[str, dict[str, torch.Tensor]]:
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder) / "tiny"
        write_tiny_dataset(root)
        return {name: recipe_parameters(root, recipe, **overrides) for name, recipe in RECIPES.items()}


def difference(before: dict[str, torch.Tensor], after: dict[str, torch.Tensor]) -> str:
    if before.keys() != after.keys():
        return f"different parameters: {sorted(before.keys() ^ after.keys())}"
    if all(torch.equal(before[name], after[name]) for name in before):
        return "equal bit for bit"
    largest = max((before[name] - after[name]).abs().max().item() for name in before)
    return f"differ, largest absolute difference {largest:.3g}"


def main(argv: list[str]) -> None:
    action, path, *flags = argv
    overrides = {}
    for flag in flags:
        key, value = flag.removeprefix("--policy.").split("=", 1)
        overrides[key] = {"true": True, "false": False}.get(value, value)
    parameters = all_recipes(**overrides)
    if action == "save":
        torch.save(parameters, path)
        print(f"saved {', '.join(parameters)} to {path}")
        return
    baseline = torch.load(path)
    for name, values in parameters.items():
        print(f"{name}: {difference(baseline[name], values)}")


if __name__ == "__main__":
    main(sys.argv[1:])
