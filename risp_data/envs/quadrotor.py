"""Quadrotor: a rigid body in free flight.

State (6): x, y, z [m], yaw, pitch, roll [rad] with R = Rz(yaw) Ry(pitch) Rx(roll) (see rotations.py).
Target (9): x, y, z, sin yaw, sin pitch, sin roll, cos yaw, cos pitch, cos roll.

Geometry constants below are shared with the simulator (risp_tasks.sims.quadrotor): rotors sit in a
"+" layout in the body frame, rotor i at ARM_LENGTH · (cos(i·π/2), sin(i·π/2), 0), i = 0..3
(0: +x, 1: +y, 2: −x, 3: −y); body x is forward, body z is the thrust axis.
"""

ARM_LENGTH = 0.3  # m, body centre to rotor axis
ROTOR_RADIUS = 0.12  # m
BODY_HALF_EXTENTS = (0.08, 0.08, 0.04)  # m
ROTOR_HEIGHT = 0.03  # m, rotor plane above the body centre

# TODO(risp-data helper): make_environment()
