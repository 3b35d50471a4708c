"""The simulator: cameras rebuild known geometry; IK is accurate and respects joint limits."""

import numpy as np
import pytest

from demo_factory.sim import HOME, TOP_DOWN, Kinematics, World, depth_to_points
from demo_factory.sim.world import JOINT_LOWER, JOINT_UPPER


@pytest.fixture(scope="module")
def world_with_box():
    with World() as world:
        box = world.add_box((0.03, 0.04, 0.05), (0.5, 0.1, 0.05), (1, 0, 0, 1), mass=0.0)
        world.step(5)
        yield world, box


def test_three_cameras_with_rgb_depth_segmentation_and_calibration(world_with_box):
    world, _ = world_with_box
    observations = world.render_cameras()
    assert list(observations) == ["left_shoulder", "right_shoulder", "wrist"]
    for obs in observations.values():
        assert obs.rgb.shape == (128, 128, 3) and obs.rgb.dtype == np.uint8
        assert obs.depth.shape == (128, 128) and obs.segmentation.shape == (128, 128)
        assert obs.intrinsics.shape == (4,) and obs.extrinsics.shape == (4, 4)


def test_point_cloud_from_depth_matches_table_and_box(world_with_box):
    world, box = world_with_box
    for name, obs in world.render_cameras().items():
        points = depth_to_points(obs.depth, obs.intrinsics, obs.extrinsics)
        table = points[obs.segmentation == world.table]
        assert len(table) > 100, name
        assert np.abs(table[:, 2]).max() < 0.003, name  # the table top is z = 0
        on_box = points[obs.segmentation == box]
        if len(on_box) < 20:
            continue  # the wrist camera may not see the box
        top = on_box[np.abs(on_box[:, 2] - 0.10) < 0.003]
        assert len(top) > 5, name  # the box's top face at z = 0.10 is seen ...
        assert np.all(np.abs(top[:, 0] - 0.5) <= 0.03 + 0.006), name  # ... within its footprint (edge pixels)
        assert np.all(np.abs(top[:, 1] - 0.1) <= 0.04 + 0.006), name
        assert on_box[:, 2].max() < 0.10 + 0.003, name


def test_camera_size_is_configurable():
    with World(image_size=(64, 96)) as world:
        obs = world.render_cameras()["wrist"]
        assert obs.rgb.shape == (64, 96, 3)
        points = depth_to_points(obs.depth, obs.intrinsics, obs.extrinsics)
        assert np.nanmax(np.abs(points[obs.segmentation == world.table][:, 2])) < 0.003


def test_ik_is_accurate_to_a_tenth_of_a_millimetre():
    kinematics = Kinematics()
    rng = np.random.default_rng(0)
    for _ in range(10):
        target = np.array([*rng.uniform([0.35, -0.25, 0.05], [0.65, 0.25, 0.3]), *TOP_DOWN])
        q = kinematics.inverse(target, seed=HOME)
        assert q is not None
        assert np.all(q >= JOINT_LOWER) and np.all(q <= JOINT_UPPER)
        assert np.linalg.norm(kinematics.forward(q)[:3] - target[:3]) <= 1e-4
    kinematics.close()


def test_ik_refuses_unreachable_poses():
    kinematics = Kinematics()
    assert kinematics.inverse([1.5, 0.0, 0.2, *TOP_DOWN]) is None
    kinematics.close()


def test_a_closed_worlds_client_serves_the_next_world_as_a_new_one():
    def run(world):
        box = world.add_box((0.03, 0.03, 0.03), (0.5, 0.0, 0.2), (0, 0, 1, 1))
        world.command_arm(np.asarray(HOME) + 0.1)
        world.step(60)
        return [box, *world.arm_state(), *world.body_pose(box), world.render_cameras()["wrist"].rgb]

    with World() as first:
        client = first.client
        first.add_box((0.02, 0.02, 0.02), (0.4, 0.2, 0.1), (1, 0, 0, 1))  # a different scene before
        first.step(30)
    with World() as reused:
        assert reused.client == client  # reset, not a new connection
        again = run(reused)
    with World() as fresh_one, World() as fresh:  # the second cannot take a spare client
        assert fresh.client != fresh_one.client
        expected = run(fresh)
    for got, want in zip(again, expected, strict=True):  # body ids, joints, box pose, image: bit for bit
        np.testing.assert_array_equal(got, want)
