"""Nerve monitor: simulated activity of the monitored nerves as the burr nears them.

In the operating room a technician watches the facial nerve's activity
(electromyography) while the surgeon drills: the nerve fires more as the burr
comes close, and bursts when it is touched. The simulator mimics that for
every structure a case marks ``monitor = true`` (see :mod:`bonesim.io.case`).

Activity law
------------
:mod:`bonesim.physics.nerve_activity`: the rate rises as the burr's surface
nears the nerve, with the force it presses with and the drill running
(parameters in ``bonesim/data/monitor.toml``); spikes are a seeded Poisson
process of that rate: the same seed and the same updates give the same spikes.

Distances
---------
Distances are measured on the case's label map at its source resolution
(:mod:`bonesim.physics.clearance`, held by the model as ``model.clearance``), not on
the engine's grid: from the burr's centre to the nearest point of the nerve's
voxels, each voxel the box of its (possibly anisotropic) spacing, exact and
sub-voxel, 0 inside; minus the burr radius for the burr's surface. One kernel
call answers every monitored nerve for all the samples of an update. Models
built from arrays (no ``clearance``) measure on their grid, the same way.

Bodies: the clearance field is static (the initial label map); a nerve is
measured in the frame of its body (:mod:`bonesim.engine.bodies`), the one
holding most of its remaining grid voxels (:meth:`NerveMonitor.follow`; body
0 at the start): the burr centre goes through ``R^T (p - t)`` first. A nerve
split across bodies is measured whole in its majority body's frame (a
limitation). Bodies at the identity pose give exactly the one-body distances.

Where it runs
-------------
:class:`NerveMonitor` is the model (no processes, no clocks: feed it
samples). :class:`MonitorProcess` runs it in a process of its own attached to
a running :class:`bonesim.runtime.haptic_loop.HapticLoop`'s shared memory: it drains
the loop's per-step ``samples`` ring (or polls its ``status`` array where the
loop has no ring) at :data:`UPDATE_HZ`, places the nerves with the loop's
shared body arrays and density as they are at each update (so the samples of
one update are all measured at the poses of its end), and publishes the
current rates and distances, a rate history and the spike times in a small shared block
(:class:`MonitorView` reads it: the window's trace, the audio process's
clicks) and, when asked, streams them to remote consoles
(:mod:`bonesim.net.monitor_link`). The haptic loop never waits for it.
"""
from __future__ import annotations

import math
import os
import time

import numpy as np
from bonesim.engine import events
from bonesim.engine.bodies import Bodies, is_identity, majority_bodies, to_body_frame
from bonesim.physics.clearance import Clearance
from bonesim.errors import BonesimError
from bonesim.io.anatomy import clinical_name
from bonesim.physics.monitor_rings import (HISTORY_CAP, HISTORY_S, SPIKE_CAP, read_history,
                                           shared_rings)
from bonesim.runtime.child import ChildProcess
from bonesim.runtime.shared import SharedArrays, read_seqlocked
from bonesim.physics.nerve_activity import (ActivityParams, activity, default_activity_params,
                                            default_params_path, load_activity_params,
                                            poisson_spikes)

__all__ = ["ActivityParams", "load_activity_params", "default_params_path", "activity",
           "NerveField", "poisson_spikes", "NerveMonitor", "monitored_structures",
           "MonitorProcess", "MonitorView", "shared_rings", "read_history", "UPDATE_HZ",
           "HISTORY_S"]

#: Rate at which the monitor process updates [Hz].
UPDATE_HZ = 200.0
#: Updates between refreshes of the measured rate and cost statistics.
STATS_EVERY = 100
#: Most nerves one monitor handles (the spike ring stores the nerve as uint8).
MAX_NERVES = 255


# --------------------------------------------------------- distance field
class NerveField:
    """Distance from any point to one nerve (a view of a :class:`Clearance`).

    Parameters
    ----------
    mask : (nx, ny, nz) bool
        The nerve's voxels.
    spacing_mm : float or (3,) float
        Voxel edge(s) along x, y, z [mm].
    origin_mm : (3,) float
        Centre of voxel (0, 0, 0) [mm].
    margin_mm : float
        Unused (the distances are exact everywhere); kept for callers.
    name : str
        For error messages.

    Attributes
    ----------
    clearance : Clearance
        The field answering the distances (:meth:`of` shares a model's).
    label : int
        The nerve's structure index in ``clearance``.
    voxels_mm : (m, 3) float64
        Centres of the nerve's surface voxels [mm] (targets for tests and
        benchmarks; the distance to the nerve is the distance to their boxes).

    Raises
    ------
    ValueError
        If the nerve has no voxels.
    """

    def __init__(self, mask, spacing_mm, origin_mm, margin_mm: float = 0.0,
                 name: str = "nerve"):
        labels = np.asarray(mask, dtype=bool).astype(np.uint8)
        self._attach(Clearance(labels, spacing_mm, origin_mm, [1]), 1, name)

    @classmethod
    def of(cls, clearance: Clearance, label: int, name: str = "nerve") -> "NerveField":
        """The field of structure ``label`` of an existing clearance field."""
        self = cls.__new__(cls)
        self._attach(clearance, label, name)
        return self

    def _attach(self, clearance: Clearance, label: int, name: str) -> None:
        self.name = name
        self.clearance = clearance
        self.label = int(label)
        self.spacing_mm = clearance.spacing_mm
        self.voxels_mm = clearance.surface_mm(self.label)
        if len(self.voxels_mm) == 0:
            raise ValueError(f"monitored structure {name!r} has no voxels")
        self._mask = clearance.group_mask([[self.label]])

    @property
    def nbytes(self) -> int:
        """Memory of the clearance field answering for it [bytes]."""
        return self.clearance.nbytes

    def distance(self, pos_mm) -> np.ndarray:
        """Distance [mm] from points ``pos_mm`` ((3,) or (n, 3)) to the nerve's
        voxels (their boxes; 0 inside); shape ``(n,)``."""
        return self.clearance.distances(pos_mm, self._mask)[:, 0]


# ------------------------------------------------------------------- model
def monitored_structures(model) -> list[tuple[int, object]]:
    """``(label, structure)`` of the model's monitored structures."""
    return [(s, st) for s, st in enumerate(model.structures, start=1)
            if getattr(st, "monitor", False)]


class NerveMonitor:
    """Activity of a model's monitored nerves, updated from tool samples.

    Parameters
    ----------
    model : Model
        Its ``clearance`` (the case's label map at source resolution) gives
        the distances to the nerves; a model without one (built from arrays)
        measures on its grid.
    params : ActivityParams, optional
        Default: the shipped ``monitor.toml``.
    seed : int
        Seed of the spike generator.
    nerves : sequence of str, optional
        Structure names to monitor; default those marked ``monitor = true``.

    Attributes
    ----------
    names : list of str
        The nerves' structure names (as the case spells them: files, JSON).
    titles : list of str
        Their clinical names, for the screen (``Facial nerve``).
    labels : list of int
        Grid label of each nerve.
    colors : (k, 3) uint8
        Display colour of each nerve.
    clearance : Clearance
        The field answering the distances (static: built from the initial
        label map).
    fields : list of NerveField
        One view of it per nerve.
    body : (k,) int64
        The body holding each nerve (:meth:`follow`); its frame is where the
        nerve is measured.
    rates_hz, distance_mm : (k,) float64
        After the last update.
    t_s : float
        Time of the last update [s] (NaN before the first).
    spikes : (t_s, nerve)
        Spikes generated by the last update.
    """

    def __init__(self, model, params: ActivityParams | None = None, seed: int = 0,
                 nerves=None):
        self.params = default_activity_params() if params is None else params
        if nerves is None:
            chosen = monitored_structures(model)
        else:
            names = [st.name for st in model.structures]
            missing = [n for n in nerves if n not in names]
            if missing:
                raise ValueError(f"no structure(s) {missing} in model {model.name!r}; "
                                 f"structures: {names}")
            chosen = [(names.index(n) + 1, model.structures[names.index(n)]) for n in nerves]
        if len(chosen) > MAX_NERVES:
            raise ValueError(f"at most {MAX_NERVES} monitored structures, got {len(chosen)}")
        self.names = [st.name for _, st in chosen]
        self.titles = [clinical_name(n) for n in self.names]
        self.labels = [lab for lab, _ in chosen]
        self.colors = np.array([st.display_color for _, st in chosen],
                               dtype=np.uint8).reshape(-1, 3)
        self.seed = int(seed)
        cl = getattr(model, "clearance", None)
        if chosen and (cl is None or not set(self.labels) <= set(cl.structures)):
            g = model.grid
            _, lab = g.to_dense()
            cl = Clearance(lab, g.spacing_mm, g.origin_mm, self.labels)
        self.clearance = cl
        self.fields = []
        for label, st in chosen:
            try:
                self.fields.append(NerveField.of(cl, label, st.name))
            except ValueError as exc:
                manifest = getattr(getattr(model, "case", None), "manifest", None)
                raise BonesimError(f"{exc}: it cannot be monitored", manifest,
                                   f"structures[{label - 1}]") from None
        self._groups = None if cl is None else cl.group_mask([[s] for s in self.labels])
        self.radius_mm = float(model.burr.radius_mm)
        # each nerve's voxels on the engine grid (brick, offset), to find its body
        lab = model.grid.label
        self._vox = [np.nonzero(lab == s) for s in self.labels]
        self.body = np.zeros(self.n, np.int64)
        self._pose_m = np.zeros((self.n, 3, 4))
        self._posed = np.zeros(self.n, bool)
        self.reset()

    @property
    def n(self) -> int:
        """Number of monitored nerves."""
        return len(self.names)

    def reset(self) -> None:
        """Back to the seeded start: no time, resting rates, no spikes."""
        self.rng = np.random.default_rng(self.seed)
        self.t_s = math.nan
        self.rates_hz = np.full(self.n, self.params.baseline_hz)
        self.distance_mm = np.full(self.n, math.inf)
        self.spikes = (np.zeros(0), np.zeros(0, dtype=np.uint8))
        self.body[:] = 0                         # a new run: one body at the identity
        self._posed[:] = False

    def follow(self, bodies, density=None) -> None:
        """Measure each nerve in the frame of the body holding most of its
        voxels now (:func:`~bonesim.engine.bodies.majority_bodies`).

        ``bodies``: the body arrays (a State, a replica's state, or a dict such
        as the haptic loop's shared arrays); ``density`` (n_bricks, 512),
        optional: only voxels still present vote (a nerve with none keeps its
        body)."""
        if isinstance(bodies, dict):
            bodies = Bodies.of(bodies)
        majority_bodies(bodies, self._vox, density, out=self.body)
        for q, b in enumerate(self.body):
            self._posed[q] = not is_identity(bodies.pose[b])
            self._pose_m[q] = bodies.pose_m[b]

    def distances(self, pos_mm, radius_mm=None) -> np.ndarray:
        """Burr surface to each nerve [mm]: centre distance minus the burr radius.

        Parameters
        ----------
        pos_mm : (3,) or (n, 3)
            Burr centres, case frame [mm]; each nerve is measured in its
            body's frame (:meth:`follow`).
        radius_mm : float or (n,), optional
            Burr radius [mm]; default the model's burr.

        Returns
        -------
        (n, k) float64
        """
        p = np.asarray(pos_mm, dtype=np.float64).reshape(-1, 3)
        r = self.radius_mm if radius_mm is None else np.asarray(radius_mm, np.float64)
        if self.n == 0:
            return np.empty((p.shape[0], 0))
        if not self._posed.any():
            out = self.clearance.distances(p, self._groups)
        else:
            out = np.empty((p.shape[0], self.n))
            for b in np.unique(self.body):
                cols = np.flatnonzero(self.body == b)
                q = cols[0]
                pb = to_body_frame(self._pose_m[q], p) if self._posed[q] else p
                out[:, cols] = self.clearance.distances(pb, self._groups[cols])
        out -= np.reshape(r, (-1, 1))
        return out

    def update_many(self, t_s, pos_mm, force_n, drill, radius_mm=None):
        """Advance through ``n`` tool samples (e.g. the haptic steps since the
        last update).

        Each sample's rate holds over the interval since the previous sample
        (the first of a run only sets the clock). Samples at or before the
        last update's time start a new clock (a new run).

        Parameters
        ----------
        t_s : (n,) float
            Sample times [s], increasing.
        pos_mm : (n, 3) float
            Burr centres [mm].
        force_n : (n,) float
            Force magnitudes [N].
        drill : (n,) bool
            Drill running.
        radius_mm : float or (n,), optional
            Burr radius [mm]; default the model's burr.

        Returns
        -------
        rates : (n, k) float64
            Rate of each nerve at each sample [spikes/s].
        distance : (n, k) float64
            Burr surface to each nerve [mm].
        """
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        if t.size == 0:
            return np.zeros((0, self.n)), np.zeros((0, self.n))
        dist = self.distances(pos_mm, radius_mm)
        rates = activity(dist, np.reshape(force_n, (-1, 1)), np.reshape(drill, (-1, 1)),
                         self.params)
        rates = np.broadcast_to(rates, dist.shape)
        if math.isnan(self.t_s) or t[0] <= self.t_s:
            edges, r = t, rates[1:]                     # the first sample sets the clock
        else:
            edges, r = np.concatenate(([self.t_s], t)), rates
        self.spikes = poisson_spikes(self.rng, edges, r) if len(r) else \
            (np.zeros(0), np.zeros(0, dtype=np.uint8))
        self.t_s = float(t[-1])
        self.rates_hz = np.array(rates[-1])
        self.distance_mm = dist[-1].copy()
        return rates, dist

    def update(self, t_s: float, pos_mm, force_n: float, drill: bool,
               radius_mm: float | None = None) -> np.ndarray:
        """Advance to one tool sample; returns the rates [spikes/s], (k,).

        The spikes of the interval since the previous update are in
        :attr:`spikes`."""
        self.update_many([t_s], np.reshape(pos_mm, (1, 3)), [force_n], [drill], radius_mm)
        return self.rates_hz.copy()


# ------------------------------------------------------- shared monitor state
#: The monitor's status fields (after the process base's).
STATUS = (
    ("updates", np.int64),
    ("rate_hz", np.float64),                # measured update rate [Hz]
    ("cost_p50_us", np.float64),            # per-update cost [us]
    ("cost_p99_us", np.float64),
    ("t_s", np.float64),                    # loop time of the last update [s]
    ("t0", np.float64),                     # monotonic clock at loop time 0 [s]
    ("source", np.uint8),                   # SOURCE_STATUS or SOURCE_SAMPLES
    ("clients", np.int64),                  # remote consoles
    ("packets", np.int64),                  # packets sent to them
    ("port", np.int64),                     # console server's UDP port
    ("stream_hz", np.float64),              # its stream rate [Hz]
)
#: Where the monitor read the loop: its status record, or its samples ring.
SOURCE_STATUS, SOURCE_SAMPLES = 1, 2


def _monitor_spec(k: int) -> list:
    k = max(k, 1)
    return [("mon.rates", (k,), np.float64),
            ("mon.dist", (k,), np.float64),
            ("hist.t_s", (HISTORY_CAP,), np.float64),
            ("hist.rate", (HISTORY_CAP, k), np.float32),
            ("hist.dist", (HISTORY_CAP, k), np.float32), ("hist.head", (1,), np.int64),
            ("spikes.t_s", (SPIKE_CAP,), np.float64),
            ("spikes.nerve", (SPIKE_CAP,), np.uint8), ("spikes.head", (1,), np.int64)]


class MonitorView:
    """Reads a monitor's shared block (window, audio, tests).

    Parameters
    ----------
    arrays : dict
        The block's arrays (from :class:`bonesim.runtime.shared.SharedArrays`).
    names : list of str
    colors : (k, 3) uint8
    params : ActivityParams
    """

    def __init__(self, arrays, names, colors, params: ActivityParams):
        self.arrays = arrays
        self.names = list(names)
        self.colors = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        self.params = params
        self.status = arrays["status"]
        self.hist, self.spike_ring = shared_rings(arrays)

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def rates_hz(self) -> np.ndarray:
        return self.arrays["mon.rates"][:self.n].copy()

    @property
    def distance_mm(self) -> np.ndarray:
        return self.arrays["mon.dist"][:self.n].copy()

    @property
    def t_s(self) -> float:
        """Loop time of the last update [s]."""
        return float(self.status["t_s"])

    @property
    def update_hz(self) -> float:
        """Measured update rate [Hz] (0 until measured)."""
        return float(self.status["rate_hz"])

    def stats(self) -> dict:
        """Measured figures: update rate [Hz], per-update cost p50/p99 [us],
        updates, source, remote consoles and packets sent."""
        s = self.status
        return {"update_hz": round(float(s["rate_hz"]), 1),
                "cost_p50_us": round(float(s["cost_p50_us"]), 1),
                "cost_p99_us": round(float(s["cost_p99_us"]), 1),
                "updates": int(s["updates"]),
                "source": {SOURCE_STATUS: "status", SOURCE_SAMPLES: "samples"}.get(
                    int(s["source"]), "none"),
                "consoles": int(s["clients"]), "packets_sent": int(s["packets"])}

    def history(self, window_s: float = HISTORY_S) -> dict:
        """The last ``window_s`` seconds (:func:`read_history`)."""
        return read_history(self.hist, self.spike_ring, self.t_s, self.n, window_s)


def _percentile_us(costs) -> tuple[float, float]:
    a = np.asarray(costs) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def _run_monitor(child, loop_handle, model, radii, params, seed, update_hz,
                 server, source) -> None:
    """Body of the monitor process (:meth:`MonitorProcess.run`)."""
    parent = os.getppid()
    sh = SharedArrays.attach(loop_handle)
    arr = child.arrays
    mstat = child.status
    nm = NerveMonitor(model, params, seed)
    nm.distances(np.zeros((1, 3)))                    # compile (or load) the kernel
    bodies = Bodies.of(sh.arrays)                     # the loop's body arrays, live
    density = sh["density"]
    k = nm.n
    hist, spikes = shared_rings(arr)
    status = sh["status"]
    radii = np.asarray(radii, dtype=np.float64)
    samples = None
    if "samples.head" in sh.arrays and source != "status":
        samples = events.ring_from_arrays("samples", sh.arrays)
        cursor = max(0, samples.count - samples.capacity // 2)   # steps taken so far
        mstat["source"] = SOURCE_SAMPLES
    else:
        mstat["source"] = SOURCE_STATUS
    srv = None
    if server is not None:
        from bonesim.net.monitor_link import MonitorServer

        srv = MonitorServer(nm.names, nm.colors, params, update_hz=update_hz, **server)
        mstat["port"] = srv.port
        mstat["stream_hz"] = srv.stream_hz
    period = 1.0 / update_hz
    clock = time.perf_counter
    t_last = -math.inf
    t0 = math.inf
    costs: list = []
    stamps: list = []
    child.ready()
    deadline = clock()
    try:
        while not child.quit and os.getppid() == parent:
            begin = clock()
            if samples is not None:
                head = samples.count
                if head - cursor > samples.capacity // 2:     # fell behind: newest only
                    cursor = head - samples.capacity // 2
                rec = None
                if head > cursor:
                    rec = np.arange(cursor, head) & (samples.capacity - 1)
                    sf = samples.fields                 # only the columns used
                    t, pos, force = sf["t_s"][rec], sf["pos_mm"][rec], sf["mag_n"][rec]
                    drill = sf["drill"][rec] != 0
                    r = radii[np.minimum(sf["burr"][rec], len(radii) - 1)]
                cursor = head
            else:
                rec = None
                snap = read_seqlocked(status, ("t_s", "pos_mm", "mag_n", "drill", "burr",
                                                 "steps"))
                tl = float(snap["t_s"]) if snap is not None else t_last
                if tl != t_last and snap["steps"] > 0:
                    rec = True
                    t = np.array([tl])
                    pos = snap["pos_mm"].reshape(1, 3)
                    force = np.array([float(snap["mag_n"])])
                    drill = np.array([snap["drill"] != 0])
                    b = int(snap["burr"])
                    r = radii[min(max(b, 0), len(radii) - 1)]
            if rec is not None and len(t):
                if t[-1] < t_last:                          # a new loop clock
                    nm.reset()
                nm.follow(bodies, density)
                rates, dist = nm.update_many(t, pos, force, drill, r)
                t_last = float(t[-1])
                t0 = min(t0, clock() - float(status["t_s"]))
                st_t, st_n = nm.spikes
                spikes.append(t_s=st_t, nerve=st_n)
                hist.append(t_s=np.array([t_last]), rate=nm.rates_hz.reshape(1, k).astype(
                    np.float32), dist=nm.distance_mm.reshape(1, k).astype(np.float32))
                arr["mon.rates"][:k] = nm.rates_hz
                arr["mon.dist"][:k] = nm.distance_mm
                mstat["t_s"] = t_last
                mstat["t0"] = t0
                mstat["updates"] += 1
                if srv is not None:
                    srv.add(t_last, nm.rates_hz, nm.distance_mm, st_t, st_n)
            if srv is not None:
                srv.poll(time.monotonic())         # the clock packets are stamped with
                mstat["clients"] = srv.n_clients
                mstat["packets"] = srv.packets_sent
            end = clock()
            costs.append(end - begin)
            stamps.append(begin)
            if len(stamps) >= STATS_EVERY:
                mstat["rate_hz"] = (len(stamps) - 1) / (stamps[-1] - stamps[0])
                mstat["cost_p50_us"], mstat["cost_p99_us"] = _percentile_us(costs)
                costs.clear()
                stamps.clear()
            deadline += period
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest)
            elif rest < -period:                  # fell behind: do not burst
                deadline = clock()
    finally:
        if srv is not None:
            srv.close()
        sh.close()


class MonitorProcess(ChildProcess):
    """Runs a :class:`NerveMonitor` beside a running haptic loop.

    Parameters
    ----------
    loop : HapticLoop
        Its shared memory is read (samples ring or status), never written.
    params : ActivityParams, optional
    seed : int
        Spike generator seed.
    update_hz : float
        Update rate [Hz].
    serve : dict, optional
        Stream to remote consoles: keyword arguments of
        :class:`bonesim.net.monitor_link.MonitorServer` (``key``, ``host``,
        ``port``, ...). None: no network.
    source : {"auto", "status"}
        ``auto`` drains the loop's per-step ``samples`` ring where it has
        one (no step is missed), else polls its ``status`` array (the
        latest step only); ``status`` always polls.

    Attributes
    ----------
    view : MonitorView
        The shared block, readable in this process.
    names : list of str
        The nerves' structure names.
    titles : list of str
        Their clinical names, for the screen.
    status : ndarray
        The shared status record (:data:`STATUS`).
    """

    NAME = "bonesim-monitor"
    STATUS = STATUS

    def __init__(self, loop, params: ActivityParams | None = None, seed: int = 0,
                 update_hz: float = UPDATE_HZ, serve: dict | None = None,
                 source: str = "auto"):
        if not update_hz > 0:
            raise ValueError(f"update_hz must be positive, got {update_hz}")
        if source not in ("auto", "status"):
            raise ValueError(f"source must be 'auto' or 'status', got {source!r}")
        self.source = source
        self.loop = loop
        self.params = default_activity_params() if params is None else params
        self.seed = int(seed)
        self.update_hz = float(update_hz)
        self.serve = serve
        chosen = monitored_structures(loop.model)
        self.names = [st.name for _, st in chosen]
        self.titles = [clinical_name(n) for n in self.names]
        colors = [st.display_color for _, st in chosen]
        if not self.names:
            raise ValueError(f"case {loop.model.name!r} monitors no structure "
                             "(set monitor = true on a nerve in its case.toml)")
        burrs = [loop.model.burr] + [b for b in loop.burrs[1:]]
        self._radii = [float(b.radius_mm) for b in burrs]
        super().__init__()                  # (its handle: the audio attaches for clicks)
        self.view = MonitorView(self.arrays, self.names, colors, self.params)

    def shared_spec(self) -> list:
        return _monitor_spec(len(self.names))

    def child_args(self) -> dict:
        return {"loop_handle": self.loop.handle, "model": self.loop.model,
                "radii": self._radii, "params": self.params, "seed": self.seed,
                "update_hz": self.update_hz, "server": self.serve, "source": self.source}

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_monitor(child, **kwargs)

    def start(self, timeout_s: float | None = None, wait: bool = True) -> "MonitorProcess":
        """Start the process; wait until it is ready (or raise).

        With ``wait`` False it returns at once (the caller starts the haptic
        loop meanwhile, then calls :meth:`wait_ready`): the monitor reads the
        loop's samples ring from its oldest kept record, so it misses no
        step the loop takes while it warms up.

        Raises
        ------
        BonesimError
            If the console server's address cannot be bound (checked here,
            so the message names it rather than a dead child process).
        ProcessFailed
            The process failed to start (:meth:`wait_ready`).
        """
        if self.serve is not None:
            from bonesim.net.monitor_link import DEFAULT_PORT
            from bonesim.net.packets import udp_socket

            port = int(self.serve.get("port", DEFAULT_PORT))
            if port != 0:
                udp_socket(self.serve.get("host", "0.0.0.0"), port).close()
        self.launch()
        return self.wait_ready(timeout_s) if wait else self

    @property
    def port(self) -> int | None:
        """UDP port the console server listens on (None without one)."""
        return int(self.status["port"]) if self.serve is not None else None

    def stats(self) -> dict:
        return self.view.stats()

    def close(self) -> None:
        """Stop the process and free the shared block; idempotent."""
        super().close()
        self.view = None
