"""The research tree: the papers' studies, the experiment runner and the benchmarks (not installed)."""
