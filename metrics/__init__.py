"""Research metrics over recorded bonesim runs.

Planned here (see ``SPEC.md``, "Metrics"): voxel visibility at removal,
Naive Bayes drilled-region correctness, force versus distance to critical
structures, force-trajectory alignment and construct-validity statistics.
They need the session recordings of a later issue; nothing is implemented yet.
"""
