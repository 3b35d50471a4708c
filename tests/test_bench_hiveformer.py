"""The bench's HiveFormer training-step figure: a real step of the reference configuration against the
kernel floor of the same step."""

import pytest
from hiveformer_fixtures import EPISODE_LENGTHS, tiny_dataset_root

from demo_factory.tools.bench import train_step_against_kernel_floor
from demo_factory.tools.reference_run import SEEN_RECIPE

__all__ = ["tiny_dataset_root"]  # the fixture is used by name


def test_train_step_is_measured_against_the_floor_of_its_own_kernels(tiny_dataset_root):
    figures = train_step_against_kernel_floor(tiny_dataset_root, steps=1, repeats=1, rounds=1)
    assert figures["n_history"] == max(EPISODE_LENGTHS) and figures["whole_episodes"]  # the plugin's default
    # Every sample a whole episode: at least the shortest episode's keyframes each.
    [keyframes] = figures["keyframes_in_batch"]  # one round, one batch
    assert keyframes >= figures["batch_size"] * min(EPISODE_LENGTHS)
    floor = figures["kernel_floor_ms"]
    assert set(floor) == {"convolutions", "attention"} and all(ms > 0 for ms in floor.values())
    assert figures["train_step_ms"] > 0
    # One round: the ratio of the unrounded times; the reported ones are rounded to 0.1 ms.
    assert figures["step_over_floor"] == pytest.approx(figures["train_step_ms"] / figures["kernel_floor_total_ms"],
                                                       abs=0.011)


def test_the_step_is_measured_in_make_references_recipe_when_given_it(tiny_dataset_root):
    figures = train_step_against_kernel_floor(tiny_dataset_root, steps=2, repeats=1, settings=SEEN_RECIPE, rounds=2)
    assert figures["whole_episodes"] is False and figures["stem_point_cloud"] is True
    # Each round draws its own batch (the tiny dataset's 19 frames: 16, then 3); a window ending at each drawn
    # keyframe supervises at least that keyframe, at most its episode.
    first, second = figures["keyframes_in_batch"]
    assert figures["batch_size"] <= first <= figures["batch_size"] * max(EPISODE_LENGTHS)
    rest = sum(EPISODE_LENGTHS) - figures["batch_size"]  # the epoch's last samples
    assert rest <= second <= rest * max(EPISODE_LENGTHS)
    assert figures["kernel_floor_total_ms"] > 0 and figures["train_step_ms"] > 0
    # Steps and floor in alternation: the ratio is the median of the two rounds' ratios.
    low, high = figures["step_over_floor_range"]
    assert figures["rounds"] == 2 and low <= figures["step_over_floor"] <= high
