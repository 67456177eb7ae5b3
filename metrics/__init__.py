"""Research metrics over recorded bonesim runs (``SPEC.md``, "Metrics").

Pure functions of session files (:func:`bonesim.session.reader.read_session`);
each module says what it measures and how, with units:

:mod:`metrics.visibility`
    Voxel visibility at removal, recomputed exactly from the file; the
    green/red view.
:mod:`metrics.forces`
    Safe forces: force and speed against the distance to a structure, per
    2 mm bin, group means with confidence intervals, limits learned from
    experts and a trainee's exceedances.
:mod:`metrics.regions`
    Naive Bayes drilled regions, scored leave-one-participant-out.
:mod:`metrics.alignment`
    Force-trajectory alignment (dynamic programming) against an expert's
    force profile; :mod:`metrics.studies.alignment_sensitivity` chose its
    defaults.
:mod:`metrics.exposure`
    How much of each structure is left under thin bone ("skeletonized").
:mod:`metrics.conduct`
    Strokes, excessive force, time near and contacts with structures,
    drilled volume, burr choice.
:mod:`metrics.final_product`
    The drilled cavity against a panel of expert runs.
:mod:`metrics.validity`
    t-test, Mann-Whitney U, effect sizes, correlations.
:mod:`metrics.report`
    A scored cohort (:class:`metrics.cohort_result.CohortResult`) as one
    self-contained HTML page: plots by group, against instructor scores,
    force against distance, visibility views, every metric's statistics.
:mod:`metrics.run`
    Every metric of one run (``bonesim metrics run``).
:mod:`metrics.cohort`
    Every run of a cohort scored on a Dask cluster, with the group
    statistics (``bonesim metrics cohort``; the record it fills is
    :mod:`metrics.cohort_result`).
:mod:`metrics.synth`
    Synthetic cohorts of scripted expert-like and novice-like runs (test
    data; ``bonesim cohort synth``).

Importing :mod:`metrics` imports none of them (they load numba kernels,
scipy and the engine); import the module you need.
"""
__all__: list = []
