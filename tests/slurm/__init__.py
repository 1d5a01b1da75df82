"""Helpers for the cluster, resume and determinism tests (a one-node Slurm, study runs)."""
