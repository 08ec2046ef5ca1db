"""The 2-D multi-modal circles POMDP of the paper's first experiment.

The paper never published its environment, so pomil defines it here:

* **Modes** are circles that all pass through the origin, each travelled in a
  fixed direction.  Default: radius 5, anti-clockwise around (0, 5) and
  clockwise around (0, -5) (the paper's Figure 1).  Any set of circles works.
* **State**: the 2-D position; every episode starts at the origin.
* **Observation**: the position only (the POMDP).  ``history=k`` observes the
  last k positions instead (oldest first, padded with the start position),
  the fully-observed setting of the original InfoGAIL paper.
* **Action**: the moving direction as a 2-D vector.  The agent moves exactly
  one unit along it, whatever its length; a vector shorter than
  ``ZERO_ACTION_EPS`` has no direction and the agent stays where it is.
  ``action_type="angle"`` takes the heading in radians instead (the paper's
  code); angles wrap, so any real number is valid.
* **Episodes** last ``episode_length`` steps (33 by default: one loop of a
  radius-5 circle is 2*pi*5 = 31.4 unit steps).  They never terminate; the
  last step is a time-limit truncation.
* **Reward**: minus the distance from the new position to the nearest mode
  circle.  Imitation learners never see it; it is a diagnostic only.

The dynamics exist once, in :class:`CirclesVecEnv` (torch, N episodes per
call, used for training).  :class:`CirclesEnv` is the Gymnasium face of the
same code with N = 1, registered as ``pomil/Circles-v0``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import torch

ENV_ID = "pomil/Circles-v0"
ZERO_ACTION_EPS = 1e-8
DEFAULT_EXPERT_NOISE = math.exp(-1.0)
DEFAULT_NONE_THRESHOLD = 1.0


@dataclass(frozen=True)
class Circle:
    """One mode: a circle through the origin, travelled in one direction."""

    center: tuple[float, float]
    """Centre (x, y); its distance to the origin must equal the radius."""
    radius: float
    """Radius in unit steps."""
    direction: int
    """+1 anti-clockwise, -1 clockwise."""

    @classmethod
    def through_origin(cls, angle_deg: float, radius: float, direction: int) -> Circle:
        """The circle of ``radius`` whose centre lies at ``angle_deg`` degrees from the x axis.

        >>> Circle.through_origin(90, 5.0, 1)
        Circle(center=(0.0, 5.0), radius=5.0, direction=1)
        """
        a = math.radians(angle_deg)
        return cls((round(radius * math.cos(a), 9) + 0.0, round(radius * math.sin(a), 9) + 0.0), radius, direction)

    def __post_init__(self) -> None:
        if self.radius <= 0:
            raise ValueError(f"circle radius must be > 0, got {self.radius}")
        if self.direction not in (1, -1):
            raise ValueError(f"circle direction must be +1 or -1, got {self.direction}")
        dist = math.hypot(*self.center)
        if abs(dist - self.radius) > 1e-6 * max(1.0, self.radius):
            raise ValueError(f"circle centred at {self.center} with radius {self.radius} does not pass "
                             f"through the origin (|centre| = {dist:.6g})")

    def with_radius(self, radius: float) -> Circle:
        """The circle of ``radius`` through the origin with the same tangent there and direction.

        >>> Circle((0.0, 5.0), 5.0, 1).with_radius(3.0)
        Circle(center=(0.0, 3.0), radius=3.0, direction=1)
        """
        return Circle.through_origin(math.degrees(math.atan2(self.center[1], self.center[0])), radius, self.direction)


def circles_preset(name: str = "two", radius: float = 5.0) -> tuple[Circle, ...]:
    """Named sets of modes: ``one`` (anti-clockwise around (0, radius)), ``two`` (the paper's)
    or ``four`` (two more on the x axis)."""
    two = (Circle((0.0, radius), radius, 1), Circle((0.0, -radius), radius, -1))
    if name == "one":
        return two[:1]
    if name == "two":
        return two
    if name == "four":
        return two + (Circle((radius, 0.0), radius, 1), Circle((-radius, 0.0), radius, -1))
    raise ValueError(f"unknown circles preset {name!r}; expected 'one', 'two' or 'four'")


@dataclass(frozen=True)
class CirclesSpec:
    """Everything that defines a circles environment (JSON-able via to_dict)."""

    circles: tuple[Circle, ...] = field(default_factory=circles_preset)
    episode_length: int = 33
    history: int = 1
    action_type: Literal["vector", "angle"] = "vector"

    def __post_init__(self) -> None:
        if len(self.circles) < 1:
            raise ValueError("need at least one circle")
        if self.episode_length < 1:
            raise ValueError(f"episode_length must be >= 1, got {self.episode_length}")
        if self.history < 1:
            raise ValueError(f"history must be >= 1, got {self.history}")
        if self.action_type not in ("vector", "angle"):
            raise ValueError(f"action_type must be 'vector' or 'angle', got {self.action_type!r}")

    @property
    def num_modes(self) -> int:
        return len(self.circles)

    @property
    def obs_dim(self) -> int:
        return 2 * self.history

    @property
    def act_dim(self) -> int:
        return 2 if self.action_type == "vector" else 1

    def to_dict(self) -> dict[str, Any]:
        return {"circles": [[*c.center, c.radius, c.direction] for c in self.circles],
                "episode_length": self.episode_length, "history": self.history, "action_type": self.action_type}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CirclesSpec:
        d = dict(d)
        if d.get("circles") is not None:
            d["circles"] = tuple(Circle((float(c[0]), float(c[1])), float(c[2]), int(c[3])) for c in d["circles"])
        else:
            d.pop("circles", None)
        return cls(**d)

    def tensors(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(centres (K, 2), radii (K,), directions (K,)) as float tensors."""
        centres = torch.tensor([c.center for c in self.circles], dtype=torch.float32, device=device)
        radii = torch.tensor([c.radius for c in self.circles], dtype=torch.float32, device=device)
        dirs = torch.tensor([float(c.direction) for c in self.circles], dtype=torch.float32, device=device)
        return centres, radii, dirs


def action_to_direction(actions: torch.Tensor, action_type: str) -> torch.Tensor:
    """Unit step (N, 2) for each action; zero where a vector action has no direction."""
    if action_type == "angle":
        heading = actions[..., 0]
        return torch.stack([torch.cos(heading), torch.sin(heading)], dim=-1)
    norm = actions.norm(dim=-1, keepdim=True)
    safe = torch.where(norm > ZERO_ACTION_EPS, norm, torch.ones_like(norm))
    return torch.where(norm > ZERO_ACTION_EPS, actions / safe, torch.zeros_like(actions))


def executed_actions(actions: torch.Tensor, action_type: str) -> torch.Tensor:
    """The actions as the environment carries them out, in the action's own shape.

    Vector actions: the unit direction (zero below ``ZERO_ACTION_EPS``), since
    the length of the vector is ignored.  Angle actions: the heading wrapped to
    (-pi, pi].  Learners feed these, not the raw samples, to the critic and
    posterior and as the previous action a_{t-1}: expert demonstrations hold
    unit vectors, so a raw Gaussian sample's length would otherwise tell the
    critic "policy" without saying anything about where the agent went.
    """
    if action_type == "angle":
        return torch.atan2(torch.sin(actions), torch.cos(actions))
    return action_to_direction(actions, action_type)


def distance_to_circles(positions: torch.Tensor, centres: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """| |p - c_k| - r_k | for every position and circle: (..., K)."""
    return ((positions.unsqueeze(-2) - centres).norm(dim=-1) - radii).abs()


class CirclesVecEnv:
    """N circles episodes stepped together in torch; all start and end together.

    ``reset() -> obs (N, obs_dim)``;
    ``step(actions (N, act_dim)) -> (obs, reward (N,), terminated (N,), truncated (N,))``.
    There is no auto-reset: after the truncating step, call ``reset`` again.
    """

    def __init__(self, spec: CirclesSpec, num_envs: int, device: torch.device | str = "cpu") -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.spec, self.num_envs, self.obs_dim, self.act_dim = spec, num_envs, spec.obs_dim, spec.act_dim
        self.device = torch.device(device)
        self.centres, self.radii, self.directions = spec.tensors(self.device)
        self.reset()
        self._needs_reset = True  # at the start, but no episode begun before reset()

    def _obs(self) -> torch.Tensor:
        return self._history.reshape(self.num_envs, -1).clone()

    def close(self) -> None:
        """Nothing to release (the :class:`pomil.envs.vec.BatchedEnv` interface)."""

    def state_dict(self) -> dict[str, Any]:
        """Nothing to keep across a resume: every episode starts at the origin."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state != {}:
            raise ValueError("the circles environment keeps no state")

    def reset(self) -> torch.Tensor:
        self.t = 0
        self._needs_reset = False
        self.positions = torch.zeros(self.num_envs, 2, device=self.device)
        self._history = torch.zeros(self.num_envs, self.spec.history, 2, device=self.device)
        return self._obs()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (the episode is over or never began)")
        expected = (self.num_envs, self.spec.act_dim)
        if tuple(actions.shape) != expected:
            raise ValueError(f"actions must have shape {expected}, got {tuple(actions.shape)}")
        actions = actions.to(self.device, torch.float32)
        self.positions = self.positions + action_to_direction(actions, self.spec.action_type)
        self._history = torch.cat([self._history[:, 1:], self.positions.unsqueeze(1)], dim=1)
        self.t += 1
        reward = -distance_to_circles(self.positions, self.centres, self.radii).min(dim=-1).values
        terminated = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        done = self.t >= self.spec.episode_length
        truncated = torch.full((self.num_envs,), done, dtype=torch.bool, device=self.device)
        self._needs_reset = done
        return self._obs(), reward, terminated, truncated


class CirclesEnv(gym.Env):
    """Gymnasium face of :class:`CirclesVecEnv` (one episode at a time).

    >>> import gymnasium as gym, pomil
    >>> env = gym.make("pomil/Circles-v0", history=1)
    >>> obs, info = env.reset(seed=0)
    >>> obs
    array([0., 0.], dtype=float32)
    """

    metadata = {"render_modes": []}

    def __init__(self, circles: Sequence[Sequence[float]] | None = None, episode_length: int = 33, history: int = 1,
                 action_type: Literal["vector", "angle"] = "vector") -> None:
        self.spec_ = CirclesSpec.from_dict({"circles": circles, "episode_length": episode_length, "history": history,
                                            "action_type": action_type})
        self._vec = CirclesVecEnv(self.spec_, 1)
        bound = float(episode_length)
        self.observation_space = gym.spaces.Box(-bound, bound, (self.spec_.obs_dim,), np.float32)
        self.action_space = (gym.spaces.Box(-1.0, 1.0, (2,), np.float32) if action_type == "vector"
                             else gym.spaces.Box(-math.pi, math.pi, (1,), np.float32))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        obs = self._vec.reset()
        return obs[0].numpy(), {"position": self._vec.positions[0].numpy().copy()}

    def step(self, action):
        act = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, -1)
        obs, reward, terminated, truncated = self._vec.step(act)
        info = {"position": self._vec.positions[0].numpy().copy()}
        return obs[0].numpy(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info


class CircleExperts:
    """Scripted experts, one per mode, acting on the true positions (N at once).

    Each heads along the chord of its circle that one unit step spans (the
    tangent turned inwards by asin(1 / 2r)), turned further towards the circle
    by ``gain`` radians per unit of distance off it (clipped to +-pi/4), plus
    Gaussian noise of std ``noise_std`` radians on the heading.  With zero
    noise, starting on the circle, every step lands exactly on the circle.
    """

    def __init__(self, spec: CirclesSpec, noise_std: float = DEFAULT_EXPERT_NOISE, gain: float = 1.0) -> None:
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std}")
        self.spec = spec
        self.noise_std = noise_std
        self.gain = gain

    def heading(self, positions: torch.Tensor, modes: torch.Tensor,
                generator: torch.Generator | None = None) -> torch.Tensor:
        centres, radii, dirs = self.spec.tensors(positions.device)
        c, r, d = centres[modes], radii[modes], dirs[modes]
        offset = positions - c
        dist = offset.norm(dim=-1)
        phi_u = torch.atan2(offset[:, 1], offset[:, 0])
        turn = torch.pi / 2 + torch.asin(0.5 / r) + (self.gain * (dist - r)).clamp(-torch.pi / 4, torch.pi / 4)
        heading = phi_u + d * turn
        if self.noise_std > 0:
            noise = torch.randn(heading.shape, generator=generator, device=heading.device)
            heading = heading + self.noise_std * noise
        return heading

    def act(self, positions: torch.Tensor, modes: torch.Tensor,
            generator: torch.Generator | None = None) -> torch.Tensor:
        """Actions (N, act_dim) in the environment's action format."""
        heading = self.heading(positions, modes, generator)
        if self.spec.action_type == "angle":
            return torch.atan2(torch.sin(heading), torch.cos(heading)).unsqueeze(-1)
        return torch.stack([torch.cos(heading), torch.sin(heading)], dim=-1)


def classify_modes(positions: np.ndarray | torch.Tensor, spec: CirclesSpec,
                   threshold: float = DEFAULT_NONE_THRESHOLD) -> np.ndarray:
    """Mode of each trajectory: the circle it stays closest to on average.

    ``positions``: (E, T, 2) visited positions.  Returns (E,) int64 mode
    indices, -1 ("none") where the mean distance to every circle exceeds
    ``threshold`` (default 1.0 unit step: a fifth of the default radius, far
    more than a noisy expert strays, see tests).
    """
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float32)
    if pos.ndim != 3 or pos.shape[-1] != 2:
        raise ValueError(f"positions must have shape (E, T, 2), got {tuple(pos.shape)}")
    centres, radii, _ = spec.tensors()
    mean_dist = distance_to_circles(pos, centres, radii).mean(dim=1)  # (E, K)
    best, mode = mean_dist.min(dim=-1)
    mode = torch.where(best <= threshold, mode, torch.full_like(mode, -1))
    return mode.numpy().astype(np.int64)


def fit_circles(positions: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares circle through each trajectory's points and the origin it starts from
    (algebraic fit: x^2 + y^2 + D x + E y + F = 0, linear in D, E, F).

    ``positions``: (E, T, 2) visited positions.  Returns (centres (E, 2), radii (E,)); a straight
    trajectory fits a very large radius (inf where the points are collinear to machine precision)."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 2:
        raise ValueError(f"positions must have shape (E, T, 2), got {pos.shape}")
    pts = np.concatenate([np.zeros((pos.shape[0], 1, 2)), pos], axis=1)
    centres, radii = np.empty((pos.shape[0], 2)), np.empty(pos.shape[0])
    for e, p in enumerate(pts):
        a = np.column_stack([p, np.ones(len(p))])
        sol, *_ = np.linalg.lstsq(a, -(p ** 2).sum(1), rcond=None)
        centres[e] = -sol[:2] / 2
        r2 = (centres[e] ** 2).sum() - sol[2]
        radii[e] = math.sqrt(r2) if np.isfinite(r2) and r2 > 0 else math.inf
    return centres, radii


def make_spec(modes: Literal["one", "two", "four"] | str = "two", radius: float = 5.0, episode_length: int = 33, *,
              history: int = 1, action_type: Literal["vector", "angle"] = "vector") -> CirclesSpec:
    return CirclesSpec(circles_preset(modes, radius), episode_length, history, action_type)
