"""Mode-recovery statistics as free functions on integer labels.

Trajectories carry a latent code (what the policy was told) and a mode (what
the classifier saw, -1 for "none").  For each code: the share of its
trajectories in each mode, its purity (largest share in one real mode), and
the majority mode.  ``modes_covered`` counts the distinct real modes that are
some code's majority mode with purity >= 0.5.  NMI is the mutual information
between code and mode ("none" counts as its own class) normalised by the
arithmetic mean of their entropies (scikit-learn's default); it is defined as
0 when either side has a single class.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def entropy(labels: np.ndarray) -> float:
    _, counts = np.unique(labels, return_counts=True)
    p = counts / counts.sum()
    return float(-(p * np.log(p)).sum())


def mutual_information(a: np.ndarray, b: np.ndarray) -> float:
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    joint = np.zeros((ai.max() + 1, bi.max() + 1))
    np.add.at(joint, (ai, bi), 1.0)
    joint /= joint.sum()
    pa, pb = joint.sum(1, keepdims=True), joint.sum(0, keepdims=True)
    nz = joint > 0
    return float((joint[nz] * np.log(joint[nz] / (pa @ pb)[nz])).sum())


def normalized_mutual_info(a: np.ndarray, b: np.ndarray) -> float:
    ha, hb = entropy(a), entropy(b)
    if ha == 0.0 or hb == 0.0:
        return 0.0
    return float(np.clip(mutual_information(a, b) / (0.5 * (ha + hb)), 0.0, 1.0))


def mode_metrics(codes: np.ndarray, modes: np.ndarray, num_codes: int, num_modes: int) -> dict[str, Any]:
    """Per-code mode shares, purity, majority mode; modes covered; NMI.

    ``codes``: (E,) in [0, num_codes) (all zeros for a policy without codes,
    with num_codes = 1); ``modes``: (E,) in [-1, num_modes).
    """
    codes = np.asarray(codes, dtype=np.int64)
    modes = np.asarray(modes, dtype=np.int64)
    if codes.shape != modes.shape or codes.ndim != 1:
        raise ValueError(f"codes and modes must be equal-length 1-D arrays, got {codes.shape} and {modes.shape}")
    per_code = []
    for c in range(num_codes):
        m = modes[codes == c]
        n = max(len(m), 1)
        share = [float((m == k).sum() / n) for k in range(num_modes)]
        per_code.append({"code": c, "episodes": int(len(m)), "mode_share": share,
                         "none_share": float((m == -1).sum() / n), "purity": float(max(share)),
                         "majority_mode": int(np.argmax(share))})
    covered = {pc["majority_mode"] for pc in per_code if pc["purity"] >= 0.5}
    purity = [pc["purity"] for pc in per_code]
    return {"per_code": per_code, "mean_purity": float(np.mean(purity)), "min_purity": float(np.min(purity)),
            "modes_covered": len(covered), "nmi": normalized_mutual_info(codes, modes),
            "overall_mode_share": [float((modes == k).mean()) for k in range(num_modes)],
            "overall_none_share": float((modes == -1).mean())}


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0 .. n-1 of ``x``, ties sharing the mean of their ranks (inf ranks last).

    >>> average_ranks(np.array([3.0, 1.0, 3.0])).tolist()
    [1.5, 0.0, 1.5]"""
    x = np.asarray(x, dtype=np.float64)
    ranks = np.empty(len(x))
    ranks[np.argsort(x, kind="stable")] = np.arange(len(x))
    _, inv = np.unique(x, return_inverse=True)
    return (np.bincount(inv, ranks) / np.bincount(inv))[inv]


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of two equally long sequences (ties: average ranks); 0 when
    either is constant.  NaN is not accepted (ValueError)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or np.isnan(x).any() or np.isnan(y).any():
        raise ValueError(f"spearman: expected two 1-D sequences of one length without NaN, got {x.shape}, {y.shape}")
    rx, ry = average_ranks(x), average_ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = np.sqrt((rx ** 2).sum() * (ry ** 2).sum())
    return float((rx * ry).sum() / denom) if denom > 0 else 0.0


EPISODE_SEGMENTS = 3
"""Per-episode purity: an episode is cut into this many consecutive parts, each classified alone."""


def coverage(modes: np.ndarray, num_modes: int) -> float:
    """How evenly a policy's episodes spread over the real modes: the entropy of their shares among the
    episodes in some mode, over log(num_modes): 1 when every mode has an equal share, 0 for one mode (or
    none, or a single mode to cover)."""
    modes = np.asarray(modes, dtype=np.int64)
    real = modes[modes >= 0]
    return shares_coverage(np.bincount(real, minlength=num_modes) / max(len(real), 1))


def shares_coverage(shares: Any) -> float:
    """:func:`coverage` from the modes' shares of all episodes (``overall_mode_share``; the rest in none)."""
    p = np.asarray(shares, dtype=np.float64)
    if len(p) < 2 or p.sum() <= 0:
        return 0.0
    p = p[p > 0] / p.sum()
    return float(-(p * np.log(p)).sum() / np.log(len(shares)))


def episode_purity(segment_modes: np.ndarray) -> dict[str, float]:
    """Whether episodes stay in one mode: ``segment_modes`` (E, S), the mode of each of S consecutive
    segments of each episode (-1: none).  ``episode_purity``: the share of episodes whose segments are
    all in one real mode; ``switch_share``: the share whose segments visit two real modes or more."""
    seg = np.asarray(segment_modes, dtype=np.int64)
    if seg.ndim != 2 or seg.shape[1] < 1:
        raise ValueError(f"segment_modes must be (episodes, segments), got {seg.shape}")
    pure = (seg >= 0).all(1) & (seg == seg[:, :1]).all(1)
    distinct = [len(set(row[row >= 0].tolist())) for row in seg]
    return {"episode_purity": float(pure.mean()), "switch_share": float(np.mean(np.array(distinct) >= 2))}
