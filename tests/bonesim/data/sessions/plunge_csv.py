"""Write plunge.csv: the 4 s scripted trajectory of the old-file fixtures.

A cutting-5mm burr, drill on at 60,000 rpm, axis -x, goes down from above the
mastoid cortex (24.25 mm) to 18.5 mm in 2 s, then sweeps up, back and forward
for 2 s. Run with any Python that has numpy: ``python plunge_csv.py OUT.csv``.
"""
import sys

import numpy as np

t = np.round(np.arange(0, 4.0001, 0.01), 2)
x = np.interp(t, [0, 0.3, 2.0, 4.0], [24.25, 21.5, 18.5, 18.5])
y = np.interp(t, [0, 2.0, 3.0, 4.0], [4.0, 4.0, 1.0, 4.0])
z = np.interp(t, [0, 2.0, 2.5, 3.5, 4.0], [-2.0, -2.0, 1.0, -4.0, -2.0])
with open(sys.argv[1], "w") as f:
    f.write("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm,direction\n")
    for i in range(len(t)):
        f.write(f"{t[i]},{x[i]},{y[i]},{z[i]},-1.0,0.0,0.0,{0 if i == 0 else 1},60000.0,1\n")
