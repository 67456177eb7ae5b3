"""Vision datasets of many recordings on the Dask cluster the metrics use.

``bonesim dataset DIR_OR_GLOB --out DIR`` renders every session file of a
folder or glob, one task per run (:func:`render_run`), on a 2-worker
``LocalCluster`` by default or a running scheduler (``--scheduler``), the
same cluster helpers as ``bonesim metrics cohort`` (:mod:`metrics.cohort`).
Each run becomes ``DIR/<run>.h5`` (or the folder ``DIR/<run>/`` with
``--layout folder``), exactly the file ``bonesim dataset RUN.h5 --out
DIR/<run>.h5`` writes. A run that fails (unreadable, another problem) fails
alone, is reported in one line, and the others are rendered.
"""
from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["output_path", "render_run", "render_many", "cmd_dataset_many"]


def output_path(out_dir, run, layout: str = "h5") -> Path:
    """Where run ``run``'s dataset goes in ``out_dir``."""
    stem = Path(run).name
    for suffix in (".h5", ".hdf5"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
    return Path(out_dir) / (stem + (".h5" if layout == "h5" else ""))


def render_run(path: str, out: str, options: dict) -> dict:
    """One task: render ``path`` into ``out`` (runs on a worker).

    Returns the summary of :func:`bonesim.render.dataset.make_dataset`, or
    ``{"file", "error"}`` with one line saying what went wrong.
    """
    from bonesim.errors import BonesimError
    from bonesim.io.loading import warmup
    from bonesim.render.dataset import make_dataset
    from bonesim.session.dataset_spec import DatasetOptions

    opts = dict(options)
    opts["size"] = tuple(opts["size"])
    try:
        warmup()
        res = make_dataset(path, out, DatasetOptions(**opts))
    except BonesimError as exc:
        return {"file": str(path), "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - one run's failure is reported, not raised
        return {"file": str(path), "error": f"{path}: {type(exc).__name__}: "
                                            f"{' '.join(str(exc).split())}"}
    res["file"] = str(path)
    return res


def render_many(runs, out_dir, options, *, layout: str = "h5", scheduler=None,
                workers: int = 2, progress=None) -> dict:
    """Render every run of a folder, glob or list into ``out_dir``.

    Parameters
    ----------
    runs : path, str or sequence
        As :func:`metrics.cohort.find_sessions`.
    out_dir : path
        Created if needed; a run whose output already exists is refused
        (reported) and skipped.
    options : DatasetOptions
    layout : {"h5", "folder"}
    scheduler : str, optional
        A running Dask scheduler's address (default: a local cluster).
    workers : int
        Worker processes of the local cluster.
    progress : callable, optional
        ``progress(done, total)`` as tasks finish.

    Returns
    -------
    dict
        ``runs`` (each run's summary or error, in run order), ``cluster``,
        ``workers``, ``failed``.
    """
    from distributed import as_completed

    from metrics.cohort import dask_client, one_line, find_sessions

    paths = find_sessions(runs)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = [None] * len(paths)
    todo = []
    for q, p in enumerate(paths):
        dst = output_path(out_dir, p, layout)
        if dst.exists():
            results[q] = {"file": str(p), "error": f"{dst}: exists; choose an empty folder"}
        else:
            todo.append((q, p, dst))
    client, cluster, label = dask_client(scheduler, workers)
    try:
        opts = options.to_dict()
        futs = [client.submit(render_run, str(p), str(dst), opts, pure=False)
                for _, p, dst in todo]
        where = {f.key: q for (q, _, _), f in zip(todo, futs)}
        n_workers = len(client.scheduler_info().get("workers", {}))
        done = len(paths) - len(todo)
        for fut in as_completed(futs, loop=client.loop):
            q = where[fut.key]
            try:
                results[q] = fut.result()
            except Exception as exc:        # a worker died, the task was lost ...
                results[q] = {"file": str(paths[q]), "error": f"{paths[q]}: {one_line(exc)}"}
            done += 1
            if progress is not None:
                progress(done, len(paths))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return {"runs": results, "cluster": label, "workers": n_workers,
            "failed": sum(1 for r in results if "error" in r)}


def cmd_dataset_many(args, options) -> int:
    """``bonesim dataset DIR_OR_GLOB --out DIR`` (called by :mod:`bonesim.cli.dataset`)."""
    from bonesim.cli.output import print_json
    from bonesim.progress import ProgressBar
    from metrics.cohort import find_sessions

    n = len(find_sessions(args.runs))
    bar = None if args.no_progress else ProgressBar(n, "datasets")
    try:
        res = render_many(args.runs, args.out, options, layout=args.layout,
                          scheduler=args.scheduler, workers=args.workers,
                          progress=None if bar is None else (lambda d, _: bar.update(d)))
    finally:
        if bar is not None:
            bar.close()
    if args.json:
        print_json(res)
    else:
        for r in res["runs"]:
            if "error" in r:
                print(r["error"], file=sys.stderr)
            else:
                print(f"{r['file']} -> {r['out']}: {r['frames']} frames in "
                      f"{r['wall_s']:.1f} s")
        print(f"{len(res['runs']) - res['failed']} of {len(res['runs'])} runs rendered on "
              f"{res['cluster']} ({res['workers']} workers)")
    return 1 if res["failed"] else 0
