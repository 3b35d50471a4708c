"""Publishing converted datasets to the Hugging Face Hub, one repository per split, with their cards.

``plan`` reads the converted folder (no network) and checks its provenance, ``hub`` talks to the Hub
(uploads, the v3.0 tag, each split's card), ``cli`` is ``demo-factory publish``. Reads a converted
dataset folder; writes only to the Hub. (The committed cards of the standard datasets are regenerated
by ``demo_factory.tools.cards``.)
"""

from demo_factory.publish.hub import PublishReport, publish
from demo_factory.publish.plan import PublishError, PublishPlan, plan_publish

__all__ = ["PublishError", "PublishPlan", "PublishReport", "plan_publish", "publish"]
