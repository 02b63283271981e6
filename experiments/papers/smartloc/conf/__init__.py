"""Hydra config entries of smartloc (on the search path of conf/train.yaml: pkg://experiments.papers.smartloc.conf)."""
