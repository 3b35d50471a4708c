"""The dataset layout HiveFormer reads: feature names and sizes, and the metadata files a dataset's maker may add.

The one definition of what the policy expects; a converter that writes such datasets (demo-factory's) imports it.
"""

IMAGES_PREFIX = "observation.images."
DEPTH_PREFIX = "observation.depth."
CALIBRATION_PREFIX = "observation.calibration."
# [fx, fy, cx, cy] + 4x4 world-from-camera transform, row-major.
CALIBRATION_DIM = 20
# [x, y, z, qx, qy, qz, qw, open]: the next keyframe's grasp-frame pose and gripper command.
ACTION_DIM = 8
# observation.state starts with the same 8 values for the current gripper; the joints after them are unused.
GRIPPER_STATE_DIM = 8
# Task string -> the instructions that say the same thing (itself included).
PARAPHRASES_FILE = "meta/task_paraphrases.json"
# Episode index -> [[n, instructions], ...]: the episode's first n keyframes also demonstrate those instructions.
RELABELS_FILE = "meta/instruction_relabels.json"
