"""Hydra config entries of p000 (on the search path of conf/train.yaml: pkg://experiments.papers.p000.conf)."""
