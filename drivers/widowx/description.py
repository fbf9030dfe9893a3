"""The WidowX 250 6DOF as Trossen Robotics publishes it (``interbotix_xsarm_descriptions``,
``urdf/wx250s.urdf.xacro``; see docs/arms.md): the robot's own data, used by the driver
(joint limits) and by the MuJoCo model (kinematics and inertias) alike."""

from __future__ import annotations

import math

#: (joint, parent offset xyz [m], axis, limits [rad], link mass [kg], CoM xyz [m],
#:  inertia (ixx, iyy, izz, ixy, ixz, iyz) [kg·m²], inertial frame yaw [rad]) from wx250s.urdf.xacro
WX250S_LINKS: list[tuple[str, tuple, tuple, tuple, float, tuple, tuple, float]] = [
    ("waist", (0, 0, 0.072), (0, 0, 1), (-3.14158, 3.14158), 0.480879, (2.23482e-5, 4.14609e-5, 0.0066287),
     (3.79e-4, 5.557e-4, 5.889e-4, 2.2e-9, -3.561e-7, 1.2245e-6), math.pi / 2),
    ("shoulder", (0, 0, 0.03865), (0, 1, 0), (-1.88496, 1.98968), 0.430811, (0.0171605, 2.725e-7, 0.191323),
     (3.463e-3, 3.587e-3, 4.566e-4, -1e-10, -2e-10, 4.272e-4), math.pi / 2),
    ("elbow", (0.04975, 0, 0.25), (0, 1, 0), (-2.14675, 1.60570), 0.234589, (0.107963, 1.15876e-4, 0),
     (3.971e-5, 8.878e-4, 8.88e-4, 2.3528e-6, 0, 0), 0.0),
    ("forearm_roll", (0.175, 0, 0), (1, 0, 0), (-3.14158, 3.14158), 0.220991, (0.0374395, 0.00522252, 0),
     (6.369e-5, 1.677e-4, 1.834e-4, -2.292e-5, 0, 0), 0.0),
    ("wrist_angle", (0.075, 0, 0), (0, 1, 0), (-1.74533, 2.14675), 0.084957, (0.04236, -1.0663e-5, 0.010577),
     (3.082e-5, 2.822e-5, 3.152e-5, 1.91e-8, 2.3e-9, 2.5481e-6), math.pi / 2),
    ("wrist_rotate", (0.065, 0, 0), (1, 0, 0), (-3.14158, 3.14158), 0.072885 + 0.034199 + 2 * 0.016246,
     (0.021631, 2.516e-7, 0.01141), (2.537e-5, 1.836e-5, 1.674e-5, 0, 0, 4.34e-7), math.pi / 2),
]
