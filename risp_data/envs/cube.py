"""Cube: a rigid cube over a floor (z = 0).

State (6): x, y, z [m] of the centre, yaw, pitch, roll [rad] (R = Rz(yaw) Ry(pitch) Rx(roll)).
Target (9): x, y, z, sin yaw, sin pitch, sin roll, cos yaw, cos pitch, cos roll.
Geometry constants are shared with the simulator (risp_tasks.sims.cube).
"""

CUBE_SIDE = 0.2  # m (edge length)
CUBE_MASS = 1.0  # kg (simulator default)

# TODO(risp-data helper): make_environment()
