"""The torch face of a batched NumPy simulator, the environment every training loop steps.

A simulator (:class:`pomil.envs.locomotion.HopperSim`, :class:`pomil.envs.batch.GymSim`)
steps N copies in NumPy; :class:`TorchVecEnv` hands its observations, rewards and ends
to the learners as tensors on their device, through an optional observation mask (the
learner's partial view).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch


@runtime_checkable
class BatchedSim(Protocol):
    """A batched simulator: N copies of one task stepped together, NumPy in and out
    (:class:`pomil.envs.locomotion.HopperSim`, :class:`pomil.envs.batch.GymSim`) or torch on a device
    (:class:`pomil.envs.warp.WarpSim`).  Copy i of ``reset(seed)`` is seeded ``seed + i``; ``reset()`` goes on
    with each copy's generator, whose states :meth:`rng_states` gives as text for a checkpoint."""

    num_envs: int
    obs_dim: int
    act_dim: int

    def reset(self, seed: int | None = None) -> Any: ...

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any]: ...

    def rng_states(self) -> list[str]: ...

    def set_rng_states(self, states: list[str]) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class BatchedEnv(Protocol):
    """What every learner steps: N episodes at once as torch tensors on its device
    (:class:`TorchVecEnv` and :class:`pomil.envs.warp.WarpVecEnv` over a :class:`BatchedSim`, and
    :class:`pomil.envs.circles.CirclesVecEnv`).  ``reset() -> obs (N, obs_dim)``; ``step(actions (N, act_dim))
    -> (obs, reward, terminated, truncated)``; ``state_dict`` / ``load_state_dict``: what a checkpoint keeps
    so that a resumed run's episodes start where the uninterrupted run's would have."""

    num_envs: int
    obs_dim: int
    act_dim: int

    def reset(self) -> torch.Tensor: ...

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def close(self) -> None: ...


class SimCopies:
    """What the batched simulators share: the per-copy NumPy generators ``_rngs``, whose
    bit-generator states :meth:`rng_states` gives as JSON text for a checkpoint (never a pickle),
    and the checks of a step's actions."""

    num_envs: int
    act_dim: int
    done: Any
    _rngs: Sequence[np.random.Generator]

    def rng_states(self) -> list[str]:
        return [json.dumps(rng.bit_generator.state) for rng in self._rngs]

    def set_rng_states(self, states: Any) -> None:
        """Put :meth:`rng_states`' texts back into the generators; ValueError when they do not fit."""
        rngs = self._rngs
        if not isinstance(states, list) or len(states) != len(rngs) or not all(isinstance(x, str) for x in states):
            raise ValueError(f"the environment's generator states are not {len(rngs)} texts")
        for rng, text in zip(rngs, states, strict=True):
            try:
                rng.bit_generator.state = json.loads(text)
            except (TypeError, ValueError, KeyError) as err:
                raise ValueError(f"an environment generator's state is damaged ({type(err).__name__})") from None

    def _check_step(self, actions: Any) -> None:
        """ValueError for actions not of shape (N, act_dim); RuntimeError when no episode is running."""
        if tuple(actions.shape) != (self.num_envs, self.act_dim):
            raise ValueError(f"actions must have shape {(self.num_envs, self.act_dim)}, got {tuple(actions.shape)}")
        if bool(self.done.all()):
            raise RuntimeError("call reset() before step() (every episode is over or none began)")


class SimState:
    """``reset``, ``close`` and ``state_dict`` / ``load_state_dict`` of a batched env over a :class:`BatchedSim`
    (``sim``) whose first reset takes a pending seed (``_seed``, None once taken; later resets continue the
    generators) and whose ``_obs`` turns the sim's observation into the learner's: what a checkpoint keeps,
    so that a resumed run's episodes start where the uninterrupted run's would have."""

    sim: Any
    _seed: int | None

    def reset(self, seed: int | None = None) -> torch.Tensor:
        seed = self._seed if seed is None else seed
        self._seed = None
        return self._obs(self.sim.reset(seed))

    def close(self) -> None:
        self.sim.close()

    def state_dict(self) -> dict[str, Any]:
        return {"seed": self._seed, "generators": self.sim.rng_states()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not isinstance(state, dict) or set(state) != {"seed", "generators"}:
            raise ValueError("the environment's state is not {seed, generators}")
        seed = state["seed"]
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
            raise ValueError(f"the environment's pending seed is {seed!r}, not an integer")
        self.sim.set_rng_states(state["generators"])
        self._seed = seed


class TorchVecEnv(SimState):
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

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        obs, reward, term, trunc = self.sim.step(actions.detach().to("cpu", torch.float64).numpy())
        as_t = lambda x, dt: torch.as_tensor(x, dtype=dt).to(self.device)  # noqa: E731
        return self._obs(obs), as_t(reward, torch.float32), as_t(term, torch.bool), as_t(trunc, torch.bool)
