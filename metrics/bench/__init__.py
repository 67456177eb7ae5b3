"""Benchmarks of the research metrics (alignment, assessment, cohort scoring,
offline visibility).

``bonesim bench`` runs them, but ``bonesim`` never imports ``metrics``: the
bench finds each one by its dotted name in its registry
(:data:`bonesim.bench.suite.BENCHMARKS`), imported only when it runs.
"""
