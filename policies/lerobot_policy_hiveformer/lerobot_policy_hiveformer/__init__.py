"""HiveFormer policy plugin for LeRobot: importing it registers `--policy.type=hiveformer` and installs
the faster keyframe-history reader (see `dataset_reading`)."""

from . import dataset_reading
from .configuration_hiveformer import HiveformerConfig
from .modeling_hiveformer import HiveformerPolicy
from .processor_hiveformer import make_hiveformer_pre_post_processors

dataset_reading.install()

__all__ = ["HiveformerConfig", "HiveformerPolicy", "make_hiveformer_pre_post_processors"]
