"""Hand: a fixed palm with five fingers and 13 revolute (flexion) joints, each in [−π/4, π/4].

State (13): joint angles [rad] in the order of JOINT_NAMES.  Target (13): the same angles.
Geometry constants are shared with the simulator (risp_tasks.sims.hand).  The palm is a box centred at
PALM_CENTER; finger f's first joint sits at FINGER_BASES[f] (palm frame = world frame, palm fixed);
each finger is a chain of links of the listed lengths, all joints of a finger flex about the same
axis FINGER_AXES[f]; at zero angles every finger points along FINGER_DIRECTIONS[f].
"""

FINGERS = ("thumb", "index", "middle", "ring", "little")
JOINTS_PER_FINGER = (2, 3, 3, 3, 2)  # 13 joints in total
JOINT_NAMES = tuple(
    f"{f}_{j}" for f, n in zip(FINGERS, JOINTS_PER_FINGER) for j in range(n)
)
JOINT_LIMIT = 0.7853981633974483  # π/4
PALM_CENTER = (0.0, 0.0, 0.5)
PALM_HALF_EXTENTS = (0.2, 0.05, 0.2)  # x (width), y (thickness), z (height); fingers point up (+z)
FINGER_BASES = (
    (-0.22, 0.0, 0.40),  # thumb, on the palm's −x side, pointing sideways-up
    (-0.15, 0.0, 0.70),
    (-0.05, 0.0, 0.70),
    (0.05, 0.0, 0.70),
    (0.15, 0.0, 0.70),
)
FINGER_DIRECTIONS = ((-0.7071067811865476, 0.0, 0.7071067811865476), (0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1))
FINGER_AXES = ((1.0, 0.0, 0.0),) * 5  # flexion about world x: a positive angle bends the finger towards −y
LINK_LENGTHS = (
    (0.12, 0.10),
    (0.14, 0.10, 0.08),
    (0.16, 0.11, 0.08),
    (0.14, 0.10, 0.08),
    (0.10, 0.08),
)
LINK_RADIUS = 0.03  # m, finger thickness (half)

# TODO(risp-data helper): make_environment()
