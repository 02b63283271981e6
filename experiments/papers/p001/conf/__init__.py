"""Hydra config entries of p001 (on the search path of conf/train.yaml: pkg://experiments.papers.p001.conf)."""
