"""The one table of learners: name -> config class, train function, help.

``pomil train <name>``, ``pomil sweep`` (its ``"learner"`` key) and the
experiments (a spec's rows) all read it.  A learner is a train function
with its config class and the config values its name fixes: the three
adversarial learners are one loop (``algos/adversarial.py``) with
``learner`` set; the reproductions' ``bc-mlp`` and ``bc-gru`` are behaviour
cloning with ``policy`` set.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pomil.errors import PomilError


@dataclass(frozen=True)
class Learner:
    """How to train one learner.

    ``module`` holds ``config`` (the config class) and ``train`` (the function
    ``train(cfg, resume=False) -> checkpoint path``); both are imported on first
    use, so that reading the table costs no torch import.  ``fixed``: config
    values the learner's name sets (not flags of its subcommand).  ``cost``: one
    run's rough wall time relative to InfoGAIL-POMDP's, measured on circles and
    Hopper; runs on Ray start the costliest first (:func:`pomil.parallel.run_jobs`)."""

    name: str
    help: str
    module: str
    config_name: str
    train_name: str
    fixed: dict[str, Any] = field(default_factory=dict)
    command: bool = True  # a ``pomil train`` subcommand (bc-mlp / bc-gru are bc with --policy)
    cost: float = 1.0
    recurrent: bool = False
    """An adversarial learner's networks: belief encoders of kind ``belief_encoder`` (else MLPs)."""
    codes: bool = False
    """An adversarial learner with latent codes (and a posterior)."""
    critic_objective: str = ""
    """An adversarial learner's critic: ``wasserstein`` or ``gan``."""

    @property
    def config(self) -> type:
        return getattr(importlib.import_module(self.module), self.config_name)

    @property
    def train(self) -> Callable[..., Path]:
        return getattr(importlib.import_module(self.module), self.train_name)

    def make_config(self, values: dict[str, Any], source: str = "config") -> Any:
        """The learner's config from ``values`` (its fixed values win)."""
        from pomil.config import from_dict

        return from_dict(self.config, {**values, **self.fixed}, source=source)


def _adversarial(name: str, text: str, cost: float, *, recurrent: bool, codes: bool, critic: str) -> Learner:
    return Learner(name, text, "pomil.algos.adversarial", "AdversarialConfig", "train_adversarial", {"learner": name},
                   cost=cost, recurrent=recurrent, codes=codes, critic_objective=critic)


def _ablation(name: str, text: str, cost: float = 1.0, **fixed: Any) -> Learner:
    """InfoGAIL-POMDP with one part taken away (``pomil reproduce`` and ``pomil sweep`` only)."""
    return Learner(name, text, "pomil.algos.adversarial", "AdversarialConfig", "train_adversarial",
                   {"learner": "infogail-pomdp", **fixed}, command=False, cost=cost)


def _bc(name: str, text: str, cost: float, **fixed: Any) -> Learner:
    return Learner(name, text, "pomil.algos.bc", "BCConfig", "train_bc", fixed, command=not fixed, cost=cost)


LEARNERS: dict[str, Learner] = {learner.name: learner for learner in (
    _bc("bc", "behaviour cloning (feed-forward, GRU, LSTM or attention policy)", 0.15),
    _bc("bc-mlp", "behaviour cloning with a feed-forward policy (current observation only)", 0.05, policy="mlp"),
    _bc("bc-gru", "behaviour cloning with a GRU policy (belief over the history)", 0.15, policy="gru"),
    _adversarial("gail", "GAIL: MLP networks, no codes, GAN discriminator", 0.4, recurrent=False, codes=False,
                 critic="gan"),
    _adversarial("infogail", "InfoGAIL: MLP networks, latent codes, Wasserstein critic", 0.55, recurrent=False,
                 codes=True, critic="wasserstein"),
    _adversarial("infogail-pomdp", "InfoGAIL-POMDP (the paper's method): separate GRU belief encoders, codes, "
                                   "Wasserstein critic", 1.0, recurrent=True, codes=True, critic="wasserstein"),
    _ablation("igp-warm-start", "ablation: InfoGAIL-POMDP's mixture warm start alone (no adversarial iteration)",
              0.3, iterations=0),
    _ablation("igp-no-mi", "ablation: InfoGAIL-POMDP without the mutual-information reward (lambda1 = 0)",
              mi_weight=0.0),
    _ablation("igp-shared-belief", "ablation: one GRU belief shared by policy, value, critic and posterior",
              belief="shared"),
    _ablation("igp-policy-belief", "ablation: a GRU belief in the policy only; value, critic and posterior "
                                   "feed-forward", belief="policy"),
    _ablation("igp-no-bc", "ablation: InfoGAIL-POMDP without the BC term in the policy loss", bc_weight=0.0),
    Learner("diffusion", "Diffusion Policy (peer): a denoiser over action horizons from recent observations, "
                         "DDIM sampling, receding horizon; no codes (optional extra pomil[diffusion])",
            "pomil.algos.diffusion", "DiffusionConfig", "train_diffusion", {"conditioning": "none"}, cost=0.75),
    Learner("diffusion-codes", "Diffusion Policy conditioned on the codes InfoGAIL-POMDP's mixture warm start assigns "
                               "to the demonstration episodes, without labels (optional extra pomil[diffusion])",
            "pomil.algos.diffusion", "DiffusionConfig", "train_diffusion", {"conditioning": "codes"}, cost=0.95),
)}
"""Every learner by name."""

ADVERSARIAL = tuple(name for name, learner in LEARNERS.items() if learner.module == "pomil.algos.adversarial")
"""The adversarial learners (one loop, configured), the ablations included."""

DIFFUSION = tuple(name for name, learner in LEARNERS.items() if learner.module == "pomil.algos.diffusion")
"""The diffusion peers (one learner, with or without codes)."""

ABLATIONS = tuple(name for name in ADVERSARIAL if name.startswith("igp-"))
"""InfoGAIL-POMDP with one part taken away (what each part adds)."""


def learner(name: str, where: str = "learner") -> Learner:
    """The learner called ``name``; a PomilError naming the choices otherwise."""
    if name not in LEARNERS:
        raise PomilError(f"{where} must be one of {sorted(LEARNERS)}, got {name!r}")
    return LEARNERS[name]
