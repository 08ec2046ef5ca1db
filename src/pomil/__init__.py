"""pomil: multi-modal imitation learning in partially observable environments."""

import pomil.envs  # noqa: F401  (registers pomil/Circles-v0)

__version__ = "0.1.0"
