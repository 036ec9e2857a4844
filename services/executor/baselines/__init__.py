"""Comparison engines for the capacity experiments (docs/baselines.md).

Kinds are listed in one place, ``ENGINES`` in services/executor/engine.py; the modules here
hold their code: ``lockstep_variants`` (disagg, static, disjoint), ``procdisagg`` (the
vLLM-Omni design), ``interdisagg`` (VLM and action stages on different GPUs) and
``stepping`` (the per-step form of each zoo model's action stage that procdisagg's
continuous batching needs).
"""
