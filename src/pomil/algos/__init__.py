"""Learners: one readable training loop each."""
