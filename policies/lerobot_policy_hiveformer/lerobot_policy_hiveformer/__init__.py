"""HiveFormer policy plugin for LeRobot: importing it registers `--policy.type=hiveformer`."""

from .configuration_hiveformer import HiveformerConfig
from .modeling_hiveformer import HiveformerPolicy
from .processor_hiveformer import make_hiveformer_pre_post_processors

__all__ = ["HiveformerConfig", "HiveformerPolicy", "make_hiveformer_pre_post_processors"]
