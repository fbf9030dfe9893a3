"""VelociRoACH MJCF model: chassis, two crank transmissions driving six C-legs, ground.

Geometry (body frame: x forward, y left, z up; SI units):

* chassis: a box 10 cm x 4 cm x 1.2 cm (the real robot is ~10 cm long, 30-55 g).
* legs: six legs, each a spoke of length ``leg_length_m`` from its hip ending in a round
  foot (a sphere of ``foot_radius_m``, the cheapest contact in MuJoCo, also on a
  heightfield); the foot rolls over the ground like the curved VelociRoACH/RHex legs
  do, and the support height ρ + e·|cos θ| of two tripods in antiphase keeps the body
  up through the whole cycle (a straight spoke would drop it at θ = 90°). Each leg has its own hinge about the
  body's y axis at its hip. The three hinges of one side are tied to each other by
  ``<equality joint>`` constraints (q_fore = q_mid = q_aft): this is the crank
  linkage of one motor. The 180° phase between fore/aft and middle legs is built
  into the geometry (the middle leg's arc is drawn rotated by π), so one joint angle
  per side is the *crank angle*. The left/right phase (alternating tripod when the
  sides are π apart) is an initial condition set in :func:`initial_crank_angles_rad`.
* transmission: a fixed tendon per side averaging its three hinges; the motor acts on
  it with ``gear=1`` so the tendon force is the crank torque [N·m] and the tendon
  velocity is the crank velocity [rad/s]. Rotor inertia reflected through the gear
  (J_rotor·G²) is the hinge ``armature``.
* motor: a ``<general>`` actuator whose control is the terminal voltage V = duty·vbat
  [V] and whose bias is the back-EMF damping, so that MuJoCo integrates the DC-motor
  torque τ = k_t·G·η·(V − k_e·G·ω_crank)/R implicitly (``implicitfast``): the
  electrical damping is stiff at 1 ms. ``forcerange`` is the crank torque limit
  (current limit of the H-bridge).
* ground: a plane for flat terrains or a heightfield generated from a seed for rough
  ones, drawn with the terrain's look (:class:`GroundLook`: a colour with random marks of
  another, a MuJoCo builtin texture), so a camera tells the terrains apart. Slope is
  applied by tilting gravity (the world frame stays level with the ground, +x uphill),
  which keeps the heightfield and the mocap frame unchanged. The heightfield is periodic:
  the backend moves the robot by one period when it nears an edge and adds the shift back
  to every reported position (an endless terrain).
* camera: ``front``, on the chassis' nose looking forward and down (``CAMERA_PITCH_DEG``)
  at the ground just ahead of the legs, like the thesis' 3.4 g monocular camera (ch. 3.3);
  rendered only when the backend's ``params.sim.camera_px`` asks for images.

Contact filtering: legs and chassis collide with the ground only (contype/conaffinity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hilstack.tasks import perturbations

#: legs: name, side (+1 left, -1 right), hip x [m], phase offset [rad] of the drawn arc
LEGS: tuple[tuple[str, int, float, float], ...] = (
    ("lf", +1, +1, 0.0),
    ("lm", +1, 0, math.pi),
    ("la", +1, -1, 0.0),
    ("rf", -1, +1, 0.0),
    ("rm", -1, 0, math.pi),
    ("ra", -1, -1, 0.0),
)
LEG_NAMES = tuple(n for n, *_ in LEGS)
assert LEG_NAMES == perturbations.LEG_NAMES  # one list of legs (the conditions name them)


#: the chassis camera: pitched down by this much from the body's x axis, vertical field of view
CAMERA_PITCH_DEG = 60.0
CAMERA_FOVY_DEG = 50.0


@dataclass(frozen=True)
class GroundLook:
    """How a terrain looks: a base colour ``rgb`` with random marks of ``mark_rgb`` covering
    the fraction ``marks`` of a ``texture_px``² texture repeated every ``tile_m`` metres."""

    rgb: tuple[float, float, float] = (0.5, 0.5, 0.5)
    mark_rgb: tuple[float, float, float] = (0.3, 0.3, 0.3)
    marks: float = 0.2
    tile_m: float = 0.1
    texture_px: int = 128


@dataclass(frozen=True)
class Geometry:
    """Dimensions and masses (SI). Defaults approximate the VelociRoACH (Haldane et al. 2013)."""

    chassis_half_m: tuple[float, float, float] = (0.05, 0.02, 0.006)
    chassis_mass_kg: float = 0.030
    leg_mass_kg: float = 0.001
    hip_spacing_m: float = 0.035
    hip_y_m: float = 0.027
    hip_z_m: float = -0.003
    leg_length_m: float = 0.010
    foot_radius_m: float = 0.008
    armature_kgm2: float = 5e-7
    hinge_damping_nms: float = 1e-5


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(v))


def _leg_xml(name: str, side: int, xsign: float, phase: float, g: Geometry) -> str:
    # the foot: a sphere of radius ``foot_radius_m`` on a spoke of length ``leg_length_m``
    # from the hip (the spoke itself is visual only). θ = 0 points the spoke down; the
    # middle leg is drawn rotated by π about the hinge axis (+y).
    e, rho = g.leg_length_m, g.foot_radius_m
    c, s = math.cos(phase), math.sin(phase)
    foot = (-s * e, 0.0, -c * e)
    pos = (xsign * g.hip_spacing_m, side * g.hip_y_m, g.hip_z_m)
    return (
        f'      <body name="leg_{name}" pos="{_fmt(pos)}">\n'
        f'        <joint name="hip_{name}" type="hinge" axis="0 1 0" armature="{g.armature_kgm2 / 3:.6g}" '
        f'damping="{g.hinge_damping_nms:.6g}"/>\n'
        f'        <geom name="{name}_spoke" type="capsule" size="0.0015" fromto="0 0 0 {_fmt(foot)}" '
        f'contype="0" conaffinity="0" mass="0" rgba=".3 .3 .3 1"/>\n'
        f'        <geom name="{name}_foot" type="sphere" size="{rho:.6g}" pos="{_fmt(foot)}" '
        f'mass="{g.leg_mass_kg:.6g}" class="leg"/>\n'
        f'      </body>'
    )


def build_mjcf(
    *,
    timestep_s: float,
    motor_gain_nm_per_v: float,
    motor_damping_nms: float,
    torque_limit_nm: float,
    friction: float,
    solref: tuple[float, float],
    solimp: tuple[float, float, float],
    slope_deg: float,
    hfield: tuple[int, float, float] | None,
    geometry: Geometry | None = None,
    look: GroundLook | None = None,
) -> str:
    """The MJCF string.

    ``motor_gain_nm_per_v`` = k_t·G·η/R (crank torque per terminal volt),
    ``motor_damping_nms`` = k_t·k_e·G²·η/R (back-EMF damping at the crank),
    ``hfield`` = (n, half size [m], max height [m]) or None for a plane,
    ``look``: the ground's texture (default: a plain grey :class:`GroundLook`).
    """
    g = geometry or Geometry()
    lk = look or GroundLook()
    slope = math.radians(slope_deg)
    grav = (-9.81 * math.sin(slope), 0.0, -9.81 * math.cos(slope))
    legs = "\n".join(_leg_xml(n, s, xs, ph, g) for n, s, xs, ph in LEGS)
    eqs = "\n".join(
        f'    <joint joint1="hip_{side}{o}" joint2="hip_{side}m" polycoef="0 1 0 0 0" '
        f'solref="0.004 1"/>'
        for side in "lr"
        for o in "fa"
    )
    tendons = "\n".join(
        f'    <fixed name="crank_{side}">' + "".join(
            f'<joint joint="hip_{side}{o}" coef="{1 / 3:.9f}"/>' for o in "fma"
        ) + "</fixed>"
        for side in "lr"
    )
    acts = "\n".join(
        f'    <general name="motor_{side}" tendon="crank_{side}" gaintype="fixed" biastype="affine" '
        f'gainprm="{motor_gain_nm_per_v:.9g}" biasprm="0 0 {-motor_damping_nms:.9g}" '
        f'forcelimited="true" forcerange="{-torque_limit_nm:.9g} {torque_limit_nm:.9g}" '
        f'ctrllimited="false"/>'
        for side in "lr"
    )
    # texuniform: texrepeat is repetitions per metre (the look does not depend on the map's size)
    ground_asset = (
        f'<texture name="ground" type="2d" builtin="flat" rgb1="{_fmt(lk.rgb)}" rgb2="{_fmt(lk.rgb)}" '
        f'mark="random" random="{lk.marks:.6g}" markrgb="{_fmt(lk.mark_rgb)}" width="{lk.texture_px}" '
        f'height="{lk.texture_px}"/>\n'
        f'    <material name="ground" texture="ground" texuniform="true" texrepeat="{1 / lk.tile_m:.6g} '
        f'{1 / lk.tile_m:.6g}" specular="0" shininess="0" reflectance="0"/>'
    )
    if hfield is None:
        ground = '<geom name="ground" type="plane" size="0 0 0.05" material="ground" class="ground"/>'
    else:
        n, half, zmax = hfield
        ground_asset += (
            f'\n    <hfield name="terrain" nrow="{n}" ncol="{n}" size="{half:.6g} {half:.6g} {zmax:.6g} 0.005"/>'
        )
        ground = '<geom name="ground" type="hfield" hfield="terrain" material="ground" class="ground"/>'
    hx, hy, hz = g.chassis_half_m
    pitch = math.radians(CAMERA_PITCH_DEG)
    # image right = the body's -y, image up = the body's +z tilted forward by the pitch
    cam_axes = (0.0, -1.0, 0.0, math.sin(pitch), 0.0, math.cos(pitch))
    return f"""
<mujoco model="velociroach">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep_s:.6g}" integrator="implicitfast" gravity="{_fmt(grav)}"
          cone="pyramidal" solver="Newton" iterations="20" ls_iterations="8">
    <flag energy="disable" filterparent="enable"/>
  </option>
  <size memory="2M"/>
  <!-- the chassis camera sees ground 2-3 cm away: a near clipping plane below that (znear is a
       fraction of the model's extent, metres on a large heightfield); a bright, even headlight -->
  <visual>
    <map znear="0.0002"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.55 0.55 0.55" specular="0 0 0"/>
  </visual>
  <default>
    <default class="ground">
      <geom contype="1" conaffinity="1" friction="{friction:.6g} 0.005 0.0001"
            solref="{solref[0]:.6g} {solref[1]:.6g}" solimp="{_fmt(solimp)}"/>
    </default>
    <default class="leg">
      <geom contype="1" conaffinity="0" condim="3" friction="{friction:.6g} 0.005 0.0001"
            solref="{solref[0]:.6g} {solref[1]:.6g}" solimp="{_fmt(solimp)}" rgba=".2 .2 .2 1"/>
    </default>
  </default>
  <asset>{ground_asset}</asset>
  <worldbody>
    {ground}
    <body name="chassis" pos="0 0 0.03">
      <freejoint name="root"/>
      <geom name="chassis" type="box" size="{hx} {hy} {hz}" mass="{g.chassis_mass_kg}"
            contype="1" conaffinity="0" friction="0.3 0.005 0.0001" rgba=".8 .5 .1 1"/>
      <site name="imu" pos="0 0 0"/>
      <camera name="front" pos="{hx:.6g} 0 {hz:.6g}" xyaxes="{_fmt(cam_axes)}" fovy="{CAMERA_FOVY_DEG:.6g}"/>
{legs}
    </body>
  </worldbody>
  <tendon>
{tendons}
  </tendon>
  <equality>
{eqs}
  </equality>
  <actuator>
{acts}
  </actuator>
  <sensor>
    <gyro name="gyro" site="imu"/>
    <accelerometer name="accel" site="imu"/>
  </sensor>
</mujoco>
"""


def heightfield(n_period: int, margin: int, correlation_cells: float, seed: int) -> np.ndarray:
    """A smooth random height map in [0, 1], periodic with ``n_period`` cells.

    Gaussian noise low-pass filtered (Gaussian kernel of ``correlation_cells``) with
    wrap-around on n_period x n_period cells, then wrap-padded by ``margin`` cells on each
    side (+1 for the closing sample): shape (n_period + 2·margin + 1)². Positions x and
    x + period see the same ground, so a robot crossing ±period/2 can be moved by one
    period and still stand on the map (see ``VelociRoachSim._wrap``). The caller scales
    it by the hfield's max height.
    """
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n_period, n_period))
    if correlation_cells > 0:
        from scipy.ndimage import gaussian_filter

        z = gaussian_filter(z, correlation_cells, mode="wrap")
    z = np.pad(z, ((margin, margin + 1), (margin, margin + 1)), mode="wrap")
    z -= z.min()
    peak = z.max()
    return (z / peak) if peak > 0 else z


def initial_crank_angles_rad(phase_lr_rad: float) -> tuple[float, float]:
    """Left and right crank angles at reset: right = left + phase (π: alternating tripod)."""
    return 0.0, phase_lr_rad
