"""Benchmark helpers: the self-contained p000 GPS/DR model, peer adapters, timing and reporting."""

__all__: list[str] = []
