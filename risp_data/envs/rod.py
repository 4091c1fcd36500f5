"""Rod: a deformable beam with both ends fixed, seen from the side.

State (10): world z [m] of the rod's centreline at the 10 sensors SENSOR_X (evenly spaced interior
points; the ends at ±ROD_LENGTH/2 are fixed at REST_HEIGHT).  Target (10): the same.
Geometry/material constants are shared with the simulator (risp_tasks.sims.rod).
"""

ROD_LENGTH = 1.0  # m, along world x, from −0.5 to +0.5
ROD_WIDTH = 0.2  # m, along world y
ROD_THICKNESS = 0.1  # m, along world z
ROD_DENSITY = 500.0  # kg/m³
REST_HEIGHT = 1.0  # m, z of the undeformed centreline
N_SENSORS = 10
SENSOR_X = tuple(-0.5 + ROD_LENGTH * (i + 1) / (N_SENSORS + 1) for i in range(N_SENSORS))

# TODO(risp-data helper): make_environment()
