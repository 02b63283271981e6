"""Hydra config entries of p003 (on the search path of conf/train.yaml: pkg://experiments.papers.p003.conf)."""
