"""The torch face of a batched NumPy simulator, the environment every training loop steps.

A simulator (:class:`pomil.envs.locomotion.HopperSim`, :class:`pomil.envs.batch.GymSim`)
steps N copies in NumPy; :class:`TorchVecEnv` hands its observations, rewards and ends
to the learners as tensors on their device, through an optional observation mask (the
learner's partial view).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


class TorchVecEnv:
    """Torch face of a NumPy batched simulator (:class:`HopperSim`,
    :class:`pomil.envs.batch.GymSim`), with an optional observation mask.

    ``reset() -> obs (N, d)``; ``step(actions) -> (obs, reward, terminated,
    truncated)`` as float32 / bool tensors on ``device``; ``observation_mask``
    is a list of indices into the simulator's observation (the learner's
    partial view).  ``full_observation`` is the last unmasked observation.
    """

    def __init__(self, sim: Any, observation_mask: list[int] | None = None, device: Any = "cpu",
                 seed: int | None = None) -> None:
        self.sim = sim
        self.num_envs = sim.num_envs
        self.device = torch.device(device)
        self.mask = None if observation_mask is None else np.asarray(observation_mask, dtype=np.int64)
        self.obs_dim = sim.obs_dim if self.mask is None else len(self.mask)
        self.act_dim = sim.act_dim
        self._seed = seed
        self.full_observation = np.zeros((sim.num_envs, sim.obs_dim))

    def _obs(self, full: np.ndarray) -> torch.Tensor:
        self.full_observation = full
        obs = full if self.mask is None else full[:, self.mask]
        return torch.as_tensor(obs, dtype=torch.float32).to(self.device)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        seed = self._seed if seed is None else seed
        self._seed = None  # seeded once; later resets continue the generators
        return self._obs(self.sim.reset(seed))

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        obs, reward, term, trunc = self.sim.step(actions.detach().to("cpu", torch.float64).numpy())
        as_t = lambda x, dt: torch.as_tensor(x, dtype=dt).to(self.device)  # noqa: E731
        return self._obs(obs), as_t(reward, torch.float32), as_t(term, torch.bool), as_t(trunc, torch.bool)

    def close(self) -> None:
        self.sim.close()
