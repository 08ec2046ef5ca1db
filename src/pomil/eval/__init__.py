"""Evaluation: rollouts, mode-recovery metrics, figures."""
