"""Write a schema-1 session with removals, injuries, a reset and a burr change."""
import sys
import numpy as np
from bonesim.engine import events
from bonesim.io.burrs import load_burr
from bonesim.runtime.haptic_loop import push_sample
from bonesim.engine.model import Sample, make_state, reset_state, step
from bonesim.io.loading import load_model
from bonesim.runtime.record import Drainer
from bonesim.session.writer import SessionWriter
from bonesim.session.header import make_header
from bonesim.session.schema import SCHEMA_VERSION
from bonesim.io.toolpath import demo_trajectory
assert SCHEMA_VERSION == 1
out = sys.argv[1]
m0 = load_model("phantom", "cutting-5mm")
d2 = load_burr("diamond-2mm")
models = [m0, m0.with_burr(d2)]
tr = demo_trajectory(m0.case, m0.burr)
state = make_state(m0)
for m in models:
    state.fit_scratch(m)
ring = events.Ring.create(1 << 14, **events.OTHER_RINGS["samples"][1])
w = SessionWriter(out, make_header(m0, [d2], input_device="scripted", participant="v1-fixture"))
dr = Drainer(w, {"samples": ring, "removed": state.removed, "injuries": state.injuries})
# a critical voxel to touch: injuries
crit = [s for s, st in enumerate(m0.structures, 1) if st.kind == "critical"]
g = m0.grid
b, off = np.argwhere(np.isin(g.label, crit) & (g.density > 0))[len(crit) * 7]
ijk = g.bricks[b] * 8 + np.array([off >> 6, (off >> 3) & 7, off & 7])
nerve_mm = np.asarray(g.origin_mm) + g.spacing_mm * ijk
epoch, burr = 0, 0
zero = np.zeros(3)
T = 1500
for q in range(T):
    t = q * 1e-3
    if q == 700:
        epoch = 1
        reset_state(models[burr], state, rings=False)
    if q == 1100:
        burr = 1
    smp = tr.sample_at(tr.start_s + 20.0 + t)
    if 1300 <= q < 1400:
        smp = smp._replace(pos_mm=nerve_mm, drill=True)
    f = step(models[burr], state, Sample(t, smp.pos_mm, smp.axis, smp.drill, smp.speed_rpm, smp.direction))
    push_sample(ring, t, state, smp.pos_mm, smp.axis, smp.drill, smp.speed_rpm, smp.direction,
                burr, epoch, 0, f, zero)
    if q % 400 == 0:
        dr.drain(); w.flush()
dr.drain()
w.close()
print(out, state.removed.count, state.injuries.count)
