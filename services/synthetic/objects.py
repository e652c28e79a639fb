"""The ten articulated objects of the ICRA-25 "Helping Hand" dataset as synthetic presets.

The paper (Pfisterer et al., ICRA 2025, section IV.A and Fig. 3) lists the objects and their joint
types but gives no dimensions; the sizes and ranges below are plausible values for common
household/hardware items of each kind, chosen once and not tuned to any estimator.

Object frame ``o`` (the frame of every vector in this module): origin on the fixed base of the
object, **x** to the right, **y** out of the mounting surface towards the person and the camera
(for objects standing on a table: towards the person), **z** up. The moving part's frame coincides
with ``o`` at the joint value ``q = 0`` (start of the demonstration); at ``q`` the part has the pose
``T_o_part(q) = exp(q * xi_o)`` with ``xi_o = [p x a, a]`` (revolute, ``q`` in rad) or ``[a, 0]``
(prismatic, ``q`` in m), linear first as in :mod:`services.common.se3`.

``grasp`` is the grasp point on the moving part (part frame = ``o`` at q = 0): the point the hand
holds (between thumb and index tip for pinches, inside the fist for power grasps). The hand's
orientation relative to the part is given by two directions in ``o``: ``hand_distal`` (wrist to
middle-finger knuckle, the hand frame's x) and ``hand_radial`` (towards the thumb, the hand frame's
y; orthogonalised against ``hand_distal``). ``occlusion`` in [0, 1] scales how often landmarks are
hidden by the object (see :mod:`services.synthetic.camera`).

=============  =====  ==========  ===============  ========  ===============  =========  =====  ==========
name           type   axis (o)    point (o) [m]    range     grasp (o) [m]    grasp      occl.  stroke [s]
=============  =====  ==========  ===============  ========  ===============  =========  =====  ==========
chain_lock     P      +x          (0, .02, 0)      0.075 m   (0, .02, 0)      pinch      0.45   1.8
slider         P      +x          (0, 0, .012)     0.10 m    (0, 0, .012)     tripod     0.30   1.6
bolt           P      +x          (0, .025, 0)     0.035 m   (0, .025, 0)     pinch      0.50   1.0
roll           P      -z          (0, .03, 0)      0.30 m    (0, .03, 0)      power      0.15   2.0
valve          R      +y          (0, .06, 0)      1.2 rad   (.035,.06,.035)  power      0.45   1.8
tension_belt   R      +x          (0, 0, .025)     1.6 rad   (0, .09, .035)   power      0.50   1.8
window_lock    R      +y          (0, 0, 0)        2.7 rad   (0,.045,-.035)   key_pinch  0.55   2.2
flap_latch     R      +x          (0, .01, 0)      1.6 rad   (0, .02, -.05)   pinch      0.35   1.4
mug            R      +x          (0,-.035,.16)    1.75 rad  (0, .035, .165)  pinch      0.40   1.4
key            R      +y          (0, 0, 0)        3.1 rad   (.006,.035, 0)   key_pinch  0.45   2.2
=============  =====  ==========  ===============  ========  ===============  =========  =====  ==========

What each object is (our reading of the paper's photos, which are not in the source text):

- chain_lock: door chain guard; the chain's end knob slides 7.5 cm along a horizontal slotted track.
- slider: a small slide latch on a horizontal surface (table/drawer top), tab pushed 10 cm.
- bolt: a barrel bolt on a door; short 3.5 cm throw, knob pinched (the lift-and-turn of the knob
  handle is not modelled: one joint per object).
- roll: a roller blind pulled down 30 cm by its bottom bar (hook/power grasp); long range.
- valve: a 10 cm handwheel on a pipe, rim grasped at 45 deg; limited (~70 deg) articulation.
- tension_belt: ratchet-strap lever lying on a table, lifted ~90 deg about its pivot pin, handle
  held 9 cm from the pin (partially hidden hand, paper Fig. 5a).
- window_lock: a window handle/sash-lock lever on a vertical pane, turned ~155 deg; lever held in
  a lateral pinch 3.5 cm from the axis, forearm roughly along the axis.
- flap_latch: a hinged flap hanging from a horizontal hinge on a vertical surface, lifted 90 deg
  by its lower edge 5 cm from the hinge.
- mug: hinged lid of a travel mug standing on a table, flipped open ~100 deg by the lid lever
  7 cm from the hinge (the other hand holding the mug is not modelled).
- key: a key in a door lock cylinder, turned ~180 deg; the axis runs along the key shaft 6 mm from
  the grasp point, forearm along the shaft, so the hand mostly rotates in place.

Ranges vary per participant and demonstration (see ``range_spread``); stroke durations are the
nominal min-jerk durations of one full stroke before participant/demonstration scaling.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

JointType = Literal["prismatic", "revolute", "rigid"]
GraspType = Literal["pinch", "tripod", "key_pinch", "power", "hook"]
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ObjectPreset:
    """One articulated object: joint, range, grasp and viewing conditions (frame ``o``, SI units)."""

    name: str
    joint_type: JointType
    # Unit joint axis in the object frame; positive q moves the part along/about it.
    axis: Vec3
    # A point on the revolute axis / on the prismatic line through the grasp [m].
    point: Vec3
    # Nominal demonstrated range of motion: rad (revolute) or m (prismatic).
    range_nominal: float
    # Relative spread of the demonstrated range over participants and demonstrations (uniform +-).
    range_spread: float
    # Grasp point on the moving part at q = 0 [m].
    grasp: Vec3
    grasp_type: GraspType
    # Hand frame x (wrist -> middle MCP) and y (towards the thumb) in the object frame at q = 0.
    hand_distal: Vec3
    hand_radial: Vec3
    # Typical occlusion of the hand by the object, 0 (never) .. 1 (heavily occluded).
    occlusion: float
    # Nominal duration of one full min-jerk stroke [s].
    stroke_duration_s: float
    # Camera viewpoint ranges around the object's +y direction [deg].
    view_elevation_deg: tuple[float, float]
    view_azimuth_deg: tuple[float, float]
    description: str
    # A re-grasp after a release goes back to the first grasp's place on the object (turning a
    # knob, valve or key in several strokes) instead of the same place on the moved handle.
    ratchet: bool = False
    # Camera distance from the object origin [m] (0.4-1.0 m for the paper's small objects).
    camera_distance_m: tuple[float, float] = (0.4, 1.0)
    # Relative spread of the object's size per demonstration: ``point`` and ``grasp`` scale by
    # U(1 - s, 1 + s) (e.g. the handle of a cabinet door 25-35 cm from its hinge).
    scale_spread: float = 0.0
    # Duration of a still hold of a rigid ("fixed handle") object [s].
    hold_s: tuple[float, float] = (3.0, 5.0)

    def __post_init__(self) -> None:
        a = np.asarray(self.axis, dtype=float)
        if abs(float(np.linalg.norm(a)) - 1.0) > 1e-9:
            raise ValueError(f"{self.name}: axis {self.axis} is not unit length")
        if self.joint_type not in ("prismatic", "revolute", "rigid"):
            raise ValueError(f"{self.name}: unknown joint type {self.joint_type!r}")
        if not 0.0 <= self.occlusion <= 1.0:
            raise ValueError(f"{self.name}: occlusion {self.occlusion} outside [0, 1]")
        if self.joint_type == "rigid":
            if self.range_nominal != 0.0 or not 0.0 < self.hold_s[0] <= self.hold_s[1]:
                raise ValueError(f"{self.name}: a rigid object has range 0 and a hold duration")
        elif self.range_nominal <= 0.0 or not 0.0 <= self.range_spread < 1.0:
            raise ValueError(f"{self.name}: bad range {self.range_nominal} +- {self.range_spread}")
        if not 0.0 < self.camera_distance_m[0] <= self.camera_distance_m[1]:
            raise ValueError(f"{self.name}: bad camera distance {self.camera_distance_m}")
        if not 0.0 <= self.scale_spread < 0.5:
            raise ValueError(f"{self.name}: scale spread {self.scale_spread} outside [0, 0.5)")
        d = np.asarray(self.hand_distal, dtype=float)
        r = np.asarray(self.hand_radial, dtype=float)
        if np.linalg.norm(np.cross(d, r)) < 1e-3 * np.linalg.norm(d) * np.linalg.norm(r):
            raise ValueError(f"{self.name}: hand_distal and hand_radial are parallel")

    def twist_object(self) -> NDArray[np.float64]:
        """Unit joint twist ``[v, w]`` (6,) in the object frame; ``exp(q * xi)`` moves the part."""
        a = np.asarray(self.axis, dtype=float)
        if self.joint_type == "rigid":
            return np.zeros(6)
        if self.joint_type == "prismatic":
            return np.concatenate([a, np.zeros(3)])
        p = np.asarray(self.point, dtype=float)
        return np.concatenate([np.cross(p, a), a])

    def hand_rotation_object(self) -> NDArray[np.float64]:
        """Rotation ``R_o_hand`` (3, 3) at q = 0: columns are the hand x (distal), y, z (dorsal)."""
        x = np.asarray(self.hand_distal, dtype=float)
        x = x / np.linalg.norm(x)
        y = np.asarray(self.hand_radial, dtype=float)
        y = y - (y @ x) * x
        y = y / np.linalg.norm(y)
        return np.stack([x, y, np.cross(x, y)], axis=1)


def mirrored(p: ObjectPreset) -> ObjectPreset:
    """The mirror image of ``p`` across its x = 0 plane (what a left hand demonstrates).

    Positions and directions map by ``S = diag(-1, 1, 1)``; a revolute axis is a pseudovector and
    maps to ``-S a``, so the same ``q`` gives the mirrored motion (``S exp(q xi) S``). The hand's
    distal and radial directions map by ``S`` as well: the right-hand grasp becomes its mirrored
    left-hand grasp (docs/synthetic.md#left-hands).
    """
    def s(v: Vec3) -> Vec3:
        return (-v[0], v[1], v[2])

    axis = s(p.axis)
    if p.joint_type == "revolute":
        axis = (-axis[0], -axis[1], -axis[2])
    el, az = p.view_elevation_deg, p.view_azimuth_deg
    return replace(p, axis=axis, point=s(p.point), grasp=s(p.grasp), hand_distal=s(p.hand_distal),
                   hand_radial=s(p.hand_radial), view_elevation_deg=el,
                   view_azimuth_deg=(-az[1], -az[0]))


def scaled(p: ObjectPreset, factor: float) -> ObjectPreset:
    """``p`` with its joint point and grasp point scaled by ``factor`` about the object origin."""
    def s(v: Vec3) -> Vec3:
        return (factor * v[0], factor * v[1], factor * v[2])

    return replace(p, point=s(p.point), grasp=s(p.grasp))


def _unit(*v: float) -> Vec3:
    a = np.asarray(v, dtype=float)
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


_WALL = ((0.0, 35.0), (-45.0, 45.0))   # vertical mounting surface: camera roughly level
_TABLE = ((25.0, 60.0), (-45.0, 45.0))  # object on a table: camera looks down

PRESETS: dict[str, ObjectPreset] = {
    p.name: p
    for p in (
        ObjectPreset(
            name="chain_lock", joint_type="prismatic", axis=(1.0, 0.0, 0.0),
            point=(0.0, 0.02, 0.0), range_nominal=0.075, range_spread=0.15,
            grasp=(0.0, 0.02, 0.0), grasp_type="pinch",
            hand_distal=_unit(0.3, -1.0, 0.0), hand_radial=(1.0, 0.0, 0.0), occlusion=0.45,
            stroke_duration_s=1.8, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="door chain guard: end knob slides along a horizontal track"),
        ObjectPreset(
            name="slider", joint_type="prismatic", axis=(1.0, 0.0, 0.0),
            point=(0.0, 0.0, 0.012), range_nominal=0.10, range_spread=0.15,
            grasp=(0.0, 0.0, 0.012), grasp_type="tripod",
            hand_distal=_unit(0.0, -1.0, -0.6), hand_radial=(1.0, 0.0, 0.0), occlusion=0.30,
            stroke_duration_s=1.6, view_elevation_deg=_TABLE[0], view_azimuth_deg=_TABLE[1],
            description="slide latch on a horizontal surface, tab pushed sideways"),
        ObjectPreset(
            name="bolt", joint_type="prismatic", axis=(1.0, 0.0, 0.0),
            point=(0.0, 0.025, 0.0), range_nominal=0.035, range_spread=0.15,
            grasp=(0.0, 0.025, 0.0), grasp_type="pinch",
            hand_distal=_unit(0.0, -1.0, 0.3), hand_radial=(1.0, 0.0, 0.0), occlusion=0.50,
            stroke_duration_s=1.0, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="barrel bolt on a door, knob pinched, short throw"),
        ObjectPreset(
            name="roll", joint_type="prismatic", axis=(0.0, 0.0, -1.0),
            point=(0.0, 0.03, 0.0), range_nominal=0.30, range_spread=0.2,
            grasp=(0.0, 0.03, 0.0), grasp_type="power",
            hand_distal=_unit(0.0, -1.0, -0.4), hand_radial=(1.0, 0.0, 0.0), occlusion=0.15,
            stroke_duration_s=2.0, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="roller blind pulled down by its bottom bar"),
        ObjectPreset(
            name="valve", joint_type="revolute", axis=(0.0, 1.0, 0.0), ratchet=True,
            point=(0.0, 0.06, 0.0), range_nominal=1.2, range_spread=0.2,
            grasp=(0.035, 0.06, 0.035), grasp_type="power",
            hand_distal=_unit(-0.4, -1.0, -0.4), hand_radial=_unit(1.0, 0.0, -1.0),
            occlusion=0.45, stroke_duration_s=1.8, view_elevation_deg=_WALL[0],
            view_azimuth_deg=_WALL[1],
            description="10 cm handwheel, rim grasped at 45 deg, limited articulation"),
        ObjectPreset(
            name="tension_belt", joint_type="revolute", axis=(1.0, 0.0, 0.0),
            point=(0.0, 0.0, 0.025), range_nominal=1.6, range_spread=0.15,
            grasp=(0.0, 0.09, 0.035), grasp_type="power",
            hand_distal=_unit(0.0, -0.5, -0.85), hand_radial=(1.0, 0.0, 0.0), occlusion=0.50,
            stroke_duration_s=1.8, view_elevation_deg=_TABLE[0], view_azimuth_deg=_TABLE[1],
            description="ratchet-strap lever on a table lifted about its pivot pin"),
        ObjectPreset(
            name="window_lock", joint_type="revolute", axis=(0.0, 1.0, 0.0),
            point=(0.0, 0.0, 0.0), range_nominal=2.7, range_spread=0.12,
            grasp=(0.0, 0.045, -0.035), grasp_type="key_pinch",
            hand_distal=_unit(0.2, -1.0, 0.0), hand_radial=(0.0, 0.0, 1.0), occlusion=0.55,
            stroke_duration_s=2.2, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="window handle lever on a vertical pane, held 3.5 cm from the axis"),
        ObjectPreset(
            name="flap_latch", joint_type="revolute", axis=(1.0, 0.0, 0.0),
            point=(0.0, 0.01, 0.0), range_nominal=1.6, range_spread=0.15,
            grasp=(0.0, 0.02, -0.05), grasp_type="pinch",
            hand_distal=_unit(0.0, -0.5, 0.85), hand_radial=(1.0, 0.0, 0.0), occlusion=0.35,
            stroke_duration_s=1.4, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="hinged flap lifted by its lower edge"),
        ObjectPreset(
            name="mug", joint_type="revolute", axis=(1.0, 0.0, 0.0),
            point=(0.0, -0.035, 0.16), range_nominal=1.75, range_spread=0.15,
            grasp=(0.0, 0.035, 0.165), grasp_type="pinch",
            hand_distal=_unit(0.0, -1.0, -0.3), hand_radial=(1.0, 0.0, 0.0), occlusion=0.40,
            stroke_duration_s=1.4, view_elevation_deg=_TABLE[0], view_azimuth_deg=_TABLE[1],
            description="travel-mug lid flipped open about its rear hinge"),
        ObjectPreset(
            name="key", joint_type="revolute", axis=(0.0, 1.0, 0.0), ratchet=True,
            point=(0.0, 0.0, 0.0), range_nominal=3.1, range_spread=0.1,
            grasp=(0.006, 0.035, 0.0), grasp_type="key_pinch",
            hand_distal=(0.0, -1.0, 0.0), hand_radial=(0.0, 0.0, 1.0), occlusion=0.45,
            stroke_duration_s=2.2, view_elevation_deg=_WALL[0], view_azimuth_deg=_WALL[1],
            description="key turned in a door lock; axis 6 mm from the grasp point"),
    )
}

# Paper order (Table II): prismatic objects first, then revolute.
OBJECTS: tuple[str, ...] = (
    "chain_lock", "slider", "bolt", "roll",
    "valve", "tension_belt", "window_lock", "flap_latch", "mug", "key",
)


def preset(name: str) -> ObjectPreset:
    """The preset called ``name`` (one of :data:`OBJECTS`); ``ValueError`` otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown object {name!r}; known: {', '.join(OBJECTS)}") from None
