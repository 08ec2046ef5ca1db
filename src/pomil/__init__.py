"""pomil: multi-modal imitation learning in partially observable environments."""

import pomil.envs  # noqa: F401  (registers the circles environment with Gymnasium)
from pomil.api import TrainedPolicy
from pomil.data import Demonstrations

__all__ = ["Demonstrations", "TrainedPolicy"]
__version__ = "0.1.0"
