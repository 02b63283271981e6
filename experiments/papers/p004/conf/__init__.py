"""Hydra config entries of p004 (on the search path of conf/train.yaml: pkg://experiments.papers.p004.conf)."""
