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
:mod:`metrics.group_stats`
    The declared design (``metrics/design.toml``): participants as the unit,
    the mixed model over sessions, Holm and Benjamini-Hochberg corrections,
    metrics left out of the tests with the reason.
:mod:`metrics.agreement`
    ICC(2,1), Bland-Altman, ROC and AUC with Newcombe's interval.
:mod:`metrics.participants`
    The participants table, with sessions (index or date) and files.
:mod:`metrics.progress`
    Learning curves per participant against the experts' band.
:mod:`metrics.exports` and :mod:`metrics.provenance`
    Visibility NRRD on the case grid, removals Parquet, statistics CSV, each
    with the bonesim version, hashes, seed and command line.
:mod:`metrics.report`
    A scored cohort (:class:`metrics.cohort_result.CohortResult`) as one
    self-contained HTML page opening with the design and provenance
    (:mod:`metrics.report_design`): plots by group, against instructor
    scores, force against distance, visibility views, every metric's
    statistics, the Naive Bayes ROC, test-retest agreement.
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
