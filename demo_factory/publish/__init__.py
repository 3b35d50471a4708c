"""Publishing converted datasets to the Hugging Face Hub, one repository per split, with their cards.

``plan`` reads the converted folder (no network), ``hub`` talks to the Hub, ``cli`` is
``demo-factory publish`` and ``cards`` regenerates the committed cards of the standard datasets.
"""

from demo_factory.publish.hub import PublishReport, publish
from demo_factory.publish.plan import PublishError, PublishPlan, plan_publish

__all__ = ["PublishError", "PublishPlan", "PublishReport", "plan_publish", "publish"]
