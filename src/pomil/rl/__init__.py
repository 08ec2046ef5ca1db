"""Reinforcement-learning kernels: GAE, PPO loss, rollout storage."""
