"""Environments: the 2-D circles POMDP (and, later, MuJoCo tasks)."""

import gymnasium as gym

from pomil.envs.circles import ENV_ID as CIRCLES_ID

if CIRCLES_ID not in gym.registry:
    gym.register(id=CIRCLES_ID, entry_point="pomil.envs.circles:CirclesEnv")
