"""demo-factory: instruction-conditioned robot manipulation demonstrations, from simulation to LeRobot."""

__version__ = "0.1.0"
