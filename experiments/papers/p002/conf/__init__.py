"""Hydra config entries of p002 (on the search path of conf/train.yaml: pkg://experiments.papers.p002.conf)."""
